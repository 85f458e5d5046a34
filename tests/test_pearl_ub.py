"""PEARL-UB: hand computations on small cases, and rollouts of sampled problems' optimal policies
against the rules (what they show while exploring, what they return in execution)."""

import itertools
from collections import deque

import gymnasium as gym
import numpy as np
import pytest

import dream_envs
from dream_envs import pearl_ub
from dream_envs.pearl_ub import execution_rules, supports, thompson_rules, thompson_value
from dream_envs.bus import (
    COLORED_DESTINATIONS,
    COLORED_STOPS,
    END_EPISODE,
    GOALS,
    MOVES,
    N_ACTIONS,
    PICKUP,
    RIDE,
    SIZE,
    goal_stop_destination,
)
from dream_envs.cook.kitchen import DONE_STAGE, cook_transition, fridge_contents, problem_id_of, recipe_stage

COLORED_DESTINATIONS_INDEX = {d: k for k, d in enumerate(COLORED_DESTINATIONS)}


def test_exported():
    assert dream_envs.pearl_ub is pearl_ub and "pearl_ub" in dream_envs.__all__


@pytest.mark.parametrize("n_actions, horizon", [(2, 1), (8, 1), (3, 2)])
def test_bandit_hand_computation(n_actions, horizon):
    # Reward-free: TS explores with a_* only when it samples problem 0 (then knows T), else guesses
    # blindly: 1/N + (1 - 1/N)/N (0.75 at |A| = 2). Rewarded: it also knows T when its guess was
    # right, and otherwise rules the guess out: (3N - 2)/N^2 (1 at |A| = 2).
    n = n_actions**horizon
    env = gym.make("MetaBandit-v0", n_actions=n_actions, horizon=horizon)
    assert pearl_ub(env) == pytest.approx(1 / n + (1 - 1 / n) / n)
    assert pearl_ub(env, rewarded_exploration=True) == pytest.approx((3 * n - 2) / n**2)
    rewarded = gym.make("MetaBandit-v0", n_actions=n_actions, horizon=horizon, reward_free_exploration=False)
    assert pearl_ub(rewarded) == pearl_ub(env, rewarded_exploration=True)  # the env's setting by default
    assert pearl_ub(gym.make("MetaBandit-v0", n_actions=2)) == pytest.approx(0.75)


@pytest.mark.parametrize("variant", ["vanilla", "map"])
@pytest.mark.parametrize("rewarded", [False, True])
def test_bus_hand_computation(variant, rewarded):
    # The explored stop is the goal's with probability 1/4 (0.8); otherwise 3 stops are left for
    # the goal: 0.8 with probability 1/3, else shuttling until the horizon (-0.1 x 20).
    env = gym.make("MetaBus-v0", variant=variant)
    value = pearl_ub(env, rewarded_exploration=rewarded)
    assert value == pytest.approx(0.25 * 0.8 + 0.75 * (0.8 / 3 + 2 / 3 * -2.0)) == pytest.approx(-0.6)
    short = gym.make("MetaBus-v0", variant=variant, horizon=5)
    assert pearl_ub(short, rewarded_exploration=rewarded) == pytest.approx(0.25 * 0.8 + 0.75 * (0.8 / 3 - 1 / 3))


def test_distracting_bus_splits_brute_force():
    # The splits weigh the colored permutations unevenly: enumerate (true, goal, explored guess,
    # its goal, execution guess) over the train split by brute force.
    env = gym.make("MetaBus-v0", variant="distracting")
    bus = env.unwrapped
    ids = bus.problem_ids("train")
    dests = [[bus.routes(int(k))[s] for s in COLORED_STOPS] for k in ids]
    # stop[k, g]: the colored stop (index) that problem k routes to the destination next to goal g.
    stop = np.array([[d.index(goal_stop_destination(g)) for g in range(4)] for d in dests])
    dest = np.array([[COLORED_DESTINATIONS_INDEX[c] for c in d] for d in dests])  # dest[k, stop]
    total = 0.0
    for s1 in range(4):  # the explored stop, and how often TS explores it
        p1 = np.mean(stop == s1)
        same = dest[:, s1][:, None] == dest[:, s1][None, :]  # [true, guess]: the ride shows the same
        hit = stop[:, None, :] == stop[None, :, :]  # [true, guess, goal]
        posterior = same / same.sum(axis=1, keepdims=True)
        p_hit = np.einsum("kj,kjg->kg", posterior, hit).mean()
        total += p1 * (p_hit * 0.8 + (1 - p_hit) * -2.0)
    assert pearl_ub(env, "train") == pytest.approx(total)
    assert pearl_ub(env, "all") == pytest.approx(-0.6)
    assert -0.62 < pearl_ub(env, "test") < -0.58


def test_cook_hand_computation():
    # Three kitchens, one recipe (2, 3): P1 = (1, 2, 3), P2 = (2, 1, 3), P3 = (2, 2, 3).
    # P1 and P3 fetch 2 from the middle fridge, P2 from the bottom corner; 3 from the top corner.
    # Exploring as P1/P3 (probability 2/3) the middle fridge shows 1 in P2 (known: 0.2) and 2 in
    # P1, P3 (which act alike: 0.4). Exploring as P2, the bottom fridge shows 1 in P1 (known: 0.4)
    # and 2 in P2, P3; the guess between them is right half the time: P3 0.5 x (0.4 + 0.2),
    # P2 0.5 x (0.2 + -2.0) (P3's middle fridge is wrong in P2).
    env = gym.make("MetaCook-v0", split="all")
    rules = thompson_rules(env.unwrapped)
    kitchens = [problem_id_of(c) for c in [(1, 2, 3), (2, 1, 3), (2, 2, 3)]]
    cases = (kitchens, [(2, 3)] * 3, [1 / 3] * 3)
    p1 = 0.4
    p3 = 2 / 3 * 0.4 + 1 / 3 * 0.5 * (0.4 + 0.2)
    p2 = 2 / 3 * 0.2 + 1 / 3 * 0.5 * (0.2 + -2.0)
    assert thompson_value(rules, cases) == pytest.approx((p1 + p2 + p3) / 3) == pytest.approx(0.2)
    assert thompson_value(rules, cases, rewarded_exploration=True) == pytest.approx(0.2)  # rewards add nothing


def _bus_policy(routes, goal):
    """The optimal policy of the problem with ``routes`` for ``goal``: a shortest path (BFS)."""
    links = {**routes, **{d: s for s, d in routes.items()}}

    def successors(cell):
        for action, (dx, dy) in MOVES.items():
            yield action, (min(max(cell[0] + dx, 0), SIZE - 1), min(max(cell[1] + dy, 0), SIZE - 1))
        if cell in links:
            yield RIDE, links[cell]

    cells = [(x, y) for x in range(SIZE) for y in range(SIZE)]
    dist = {goal: 0}
    queue = deque([goal])
    while queue:  # the graph is undirected (moves and two-way links): BFS from the goal
        cell = queue.popleft()
        for _, nxt in successors(cell):
            if nxt not in dist:
                dist[nxt] = dist[cell] + 1
                queue.append(nxt)
    return {c: min(successors(c), key=lambda an: (dist[an[1]], an[0]))[0] for c in cells if c != goal}


def _play_execution(env, problem_id, instruction, policy):
    """Skip exploration (end-episode), then run ``policy(inner obs) -> action``; the execution return."""
    obs, info = env.reset(options={"problem_id": problem_id, "instruction": instruction})
    obs, _, terminated, truncated, info = env.step(END_EPISODE)
    while not (terminated or truncated):
        obs, _, terminated, truncated, info = env.step(policy(obs["obs"]))
    return info["execution_returns"][0]


def _play_exploration(env, problem_id, policy, done):
    """Run ``policy(inner obs) -> action`` in a reward-free exploration episode of ``problem_id``
    until ``done(inner obs)`` (then end the episode, as TS's convention) or the horizon; the
    (obs, action, next obs) steps."""
    obs, info = env.reset(options={"problem_id": problem_id})
    steps = []
    while int(obs["phase"]) == 0:
        state = obs["obs"]
        action = END_EPISODE if done(state) else policy(state)
        obs, _, _, _, info = env.step(action)
        steps.append((state, action, info["final_obs"] if info.get("episode_end") else obs["obs"]))
    return steps


@pytest.mark.parametrize("variant", ["distracting", "map"])
def test_bus_exploration_shows_one_route(variant):
    # TS's exploration episode (the BFS-optimal policy of a sampled problem and goal, played in the
    # true problem) rides one colored route only, never a gray bus, never the map: what the rules observe.
    env = gym.make("MetaBus-v0", variant=variant)
    bus = env.unwrapped
    rules = thompson_rules(bus)
    rng = np.random.default_rng(1)
    for true, guess, g in zip(rng.integers(bus.n_problems, size=30), rng.integers(bus.n_problems, size=30),
                              rng.integers(4, size=30)):  # fmt: skip
        policy = _bus_policy(bus.routes(int(guess)), GOALS[g])
        steps = _play_exploration(
            env, int(true), lambda s: policy[(int(s[0]), int(s[1]))], lambda s: (int(s[0]), int(s[1])) == GOALS[g]
        )
        routes = bus.routes(int(true))
        ridden = {(int(s[0]), int(s[1])): (int(n[0]), int(n[1])) for s, a, n in steps if a == RIDE}
        ((_, stop),) = rules.behaviours(int(guess), (int(g) + 1,))
        assert ridden[stop] == rules.observe(int(true), stop, (int(g) + 1,), False) == routes[stop]
        assert set(ridden) <= {stop, routes[stop]}  # shuttling rides the same route back
        assert not any(len(n) > 3 and n[3] for _, _, n in steps)  # the map is never read


@pytest.mark.parametrize(
    "true, guess, recipe",
    [((1, 2, 3), (4, 2, 3), (2, 3)), ((2, 1, 3), (4, 2, 3), (2, 3)), ((3, 2, 4), (4, 2, 3), (2, 3)),
     ((5, 5, 5), (5, 6, 5), (5, 6))],
)  # fmt: skip
def test_cook_exploration_shows_the_rules_fridges(true, guess, recipe):
    # The optimal policy of the guess, played reward-free in the true kitchen: its pickups show the
    # first fridge's content, and the second's only if the first held the recipe's first ingredient.
    env = gym.make("MetaCook-v0", split="all")
    policy = _cook_policy(guess, recipe)
    steps = _play_exploration(
        env, problem_id_of(true), policy, lambda s: recipe_stage(s[3], (s[4], s[5]), recipe) == DONE_STAGE
    )
    shown = tuple(dict.fromkeys((int(s[1]), int(n[3])) for s, a, n in steps if a == PICKUP and int(s[0]) == 2))
    rules = thompson_rules(env.unwrapped)
    # Where two corner fridges tie, the BFS took one of them: the rules' behaviour that matches it.
    choices = [b for _, b in rules.behaviours(problem_id_of(guess), recipe)]
    (fridges,) = [b for b in choices if [k for k, _ in shown] == list(dict.fromkeys(b))[: len(shown)]]
    assert tuple(content for _, content in shown) == rules.observe(problem_id_of(true), fridges, recipe, False)


def test_bus_rollouts_match_the_rules():
    # Play the BFS-optimal policy of a guessed problem in the true one: 0.8 or -2.0 as derived.
    env = gym.make("MetaBus-v0", variant="vanilla")
    bus = env.unwrapped
    rng = np.random.default_rng(0)
    returns = []
    for true, guess, g in zip(rng.integers(24, size=40), rng.integers(24, size=40), rng.integers(4, size=40)):
        policy = _bus_policy(bus.routes(int(guess)), GOALS[g])
        ret = _play_execution(env, int(true), [g + 1], lambda s: policy[(int(s[0]), int(s[1]))])
        stop = [s for s in COLORED_STOPS if bus.routes(int(guess))[s] == goal_stop_destination(g)][0]
        expected = 0.8 if bus.routes(int(true))[stop] == goal_stop_destination(g) else -2.0
        assert ret == pytest.approx(expected)
        returns.append(ret)
    assert {round(r, 6) for r in returns} == {0.8, -2.0}


def _cook_policy(contents, instruction):
    """The optimal policy of fridges ``contents`` for a recipe: fewest steps to the done stage."""
    actions = [a for a in range(N_ACTIONS) if a != END_EPISODE]
    states = list(itertools.product(range(3), range(3), range(8), range(8), range(8)))
    succ = {s: [cook_transition(s, a, contents, instruction)[0] for a in actions] for s in states}
    pred = {s: [] for s in states}
    for s, nexts in succ.items():
        for n in nexts:
            pred[n].append(s)
    done = [s for s in states if recipe_stage(s[2], (s[3], s[4]), instruction) == DONE_STAGE]
    dist = dict.fromkeys(done, 0)
    queue = deque(done)
    while queue:
        s = queue.popleft()
        for p in pred[s]:
            if p not in dist:
                dist[p] = dist[s] + 1
                queue.append(p)

    def act(state):
        s = tuple(int(v) for v in state[:2]) + tuple(int(v) for v in state[3:6])
        return actions[min(range(len(actions)), key=lambda j: (dist.get(succ[s][j], 99), j))]

    return act


@pytest.mark.parametrize(
    "true, guess, expected",
    [
        ((1, 2, 3), (4, 2, 3), 0.4),  # both fetched from the middle and the top corner: 1 - 0.2 (1 + 2)
        ((2, 1, 3), (4, 2, 3), -2.0),  # the middle fridge holds 1, not 2: picks up 1 forever
        ((3, 2, 4), (4, 2, 3), 0.5 - 1.8),  # 2 cooked, then the top fridge holds 4, not 3
    ],
)
def test_cook_rollouts_match_the_rules(true, guess, expected):
    env = gym.make("MetaCook-v0", split="all")
    instruction = (2, 3)
    policy = _cook_policy(guess, instruction)
    assert _play_execution(env, problem_id_of(true), list(instruction), policy) == pytest.approx(expected)
    behaviours, execution_return = execution_rules(env.unwrapped)
    ((weight, fridges),) = behaviours(problem_id_of(guess), instruction)
    assert weight == 1.0 and execution_return(problem_id_of(true), fridges, instruction) == pytest.approx(expected)


def test_cook_values():
    # Exploring tells TS where the first ingredient is (and the second when the first was right),
    # so it beats the blind guess, and stays below the optimal 0.2..0.6; rewards help in the
    # enumeration only through the exploration instruction, which narrows the prior.
    env = gym.make("MetaCook-v0")
    for split in ("train", "test", "all"):
        value = pearl_ub(env, split)
        assert -1.0 < value < pearl_ub(env, split, rewarded_exploration=True) < 0.2
    assert fridge_contents(0) == (1, 1, 1)


def test_sign_nav_values():
    from dream_envs.sign_nav import SignNav3DEnv

    # The value needs only the trial distribution; build the env only where OpenGL is available.
    stub = SignNav3DEnv.__new__(SignNav3DEnv)
    stub.split, stub.instruction_nvec, stub.reward_free_exploration = "test", np.array([4]), True
    assert pearl_ub(stub) == pytest.approx(0.5 * 1 + 0.5 * -1)  # the touch shows nothing
    assert pearl_ub(stub, rewarded_exploration=True) == pytest.approx(1.0)  # its reward tells the colour
    assert supports(stub)


def test_supports():
    assert supports(gym.make("MetaBus-v0")) and supports(gym.make("MetaCook-v0"))
    assert not supports(gym.make("CartPole-v1"))
    with pytest.raises(TypeError, match="does not know"):
        pearl_ub(gym.make("CartPole-v1"))


def test_sign_nav_rollouts():
    from dream_envs.sign_nav import opengl_available

    ok, why = opengl_available()
    if not ok:
        pytest.skip(f"OpenGL unavailable: {why}")
    env = gym.make("SignNav3D-v0")
    oracle = dream_envs.make_oracle(env)
    total = 0.0
    for true, guess, i in itertools.product(range(2), range(2), range(1, 4)):
        oracle.reset()
        oracle.colour = guess  # the optimal policy of the guessed sign colour
        obs, info = env.reset(seed=true * 10 + i, options={"problem_id": true, "instruction": [i]})
        terminated = truncated = False
        while not (terminated or truncated):
            obs, _, terminated, truncated, info = env.step(oracle.act(obs, info))
        ret = info["execution_returns"][0]
        assert ret == (1.0 if guess == true else -1.0)
        total += ret / 12
    assert total == pytest.approx(pearl_ub(env))
