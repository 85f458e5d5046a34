"""PEARL-UB: hand computations on small cases, and rollouts of guessed problems' optimal policies."""

import itertools
from collections import deque

import gymnasium as gym
import numpy as np
import pytest

import dream_envs
from dream_envs import pearl_ub
from dream_envs.pearl_ub import execution_rules
from dream_envs.bus import COLORED_STOPS, END_EPISODE, GOALS, MOVES, RIDE, SIZE, goal_stop_destination
from dream_envs.bus import N_ACTIONS
from dream_envs.cook.kitchen import DONE_STAGE, cook_transition, fridge_contents, problem_id_of, recipe_stage


def test_exported():
    assert dream_envs.pearl_ub is pearl_ub and "pearl_ub" in dream_envs.__all__


@pytest.mark.parametrize("n_actions, horizon", [(2, 1), (8, 1), (3, 2)])
def test_bandit_is_a_blind_guess(n_actions, horizon):
    # Guessing one of |A|^H sequences: 1/2 for |A| = 2, H = 1.
    env = gym.make("MetaBandit-v0", n_actions=n_actions, horizon=horizon)
    assert pearl_ub(env) == pytest.approx(1.0 / n_actions**horizon)


@pytest.mark.parametrize("variant", ["vanilla", "map"])
def test_bus_hand_computation(variant):
    # Right bus with probability 1/4 (return 0.8), else shuttling until the horizon (-0.1 x 20).
    env = gym.make("MetaBus-v0", variant=variant)
    assert pearl_ub(env) == pytest.approx(0.25 * 0.8 + 0.75 * -2.0)
    short = gym.make("MetaBus-v0", variant=variant, horizon=5)
    assert pearl_ub(short) == pytest.approx(0.25 * 0.8 + 0.75 * -0.5)


def test_distracting_bus_splits_brute_force():
    # The splits weigh the colored permutations unevenly: count agreeing (true, guess, goal) triples.
    env = gym.make("MetaBus-v0", variant="distracting")
    bus = env.unwrapped
    for split in ("train", "test"):
        ids = bus.problem_ids(split)
        # stop[k, g]: the colored stop that problem k routes to the destination next to goal g.
        dests = [[bus.routes(int(k))[s] for s in COLORED_STOPS] for k in ids]
        stop = np.array([[d.index(goal_stop_destination(g)) for g in range(4)] for d in dests])
        agree = np.mean(stop[:, None, :] == stop[None, :, :])  # over (true, guess, goal)
        assert pearl_ub(env, split) == pytest.approx(agree * 0.8 + (1 - agree) * -2.0)
    assert pearl_ub(env, "all") == pytest.approx(-1.3)


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


def test_cook_value_bounds():
    env = gym.make("MetaCook-v0")
    for split in ("train", "test", "all"):
        value = pearl_ub(env, split)
        assert -2.0 < value < 0.6
    assert fridge_contents(0) == (1, 1, 1)


def test_sign_nav_is_zero():
    from dream_envs.sign_nav import SignNav3DEnv

    # The value needs only the trial distribution; build the env only where OpenGL is available.
    stub = SignNav3DEnv.__new__(SignNav3DEnv)
    stub.split, stub.instruction_nvec = "test", np.array([4])
    assert pearl_ub(stub) == pytest.approx(0.5 * 1 + 0.5 * -1)


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
