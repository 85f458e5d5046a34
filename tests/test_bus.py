"""MetaBus-v0: dynamics, rewards, splits, the trial contract and the oracle, on all three variants."""

from __future__ import annotations

import itertools
from typing import Any, Dict, List, Sequence

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import dream_envs  # noqa: F401  (registers the env IDs)
from dream_envs import EXECUTION, EXPLORATION, RandomAgent, ScriptedAgent, make_oracle, play_trial, public_info
from dream_envs.bus import (
    COLORED_DESTINATIONS,
    COLORED_STOPS,
    DOWN,
    DROP,
    END_EPISODE,
    GOALS,
    GRAY_DESTINATIONS,
    GRAY_STOPS,
    LEFT,
    MAP_CELL,
    NOOP,
    PERMUTATIONS,
    PICKUP,
    RIDE,
    RIGHT,
    START,
    UP,
    BusExplorationReport,
    MetaBusEnv,
    bus_stop_of,
    discovery_rewards,
    exploration_report,
    shows_map,
)

VARIANTS = ("distracting", "map", "vanilla")


def make(variant: str = "distracting", **kwargs: Any) -> MetaBusEnv:
    return gym.make("MetaBus-v0", variant=variant, **kwargs).unwrapped


def pos(obs: Dict[str, Any]) -> tuple:
    return int(obs["obs"][0]), int(obs["obs"][1])


def run(env: MetaBusEnv, actions: Sequence[int]) -> List[tuple]:
    """Step ``actions``; return the (obs, reward, terminated, info) of each step."""
    out = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        assert not truncated
        out.append((obs, reward, terminated, info))
    return out


def start_execution(env: MetaBusEnv, problem_id: int, goal: int, **reset_kwargs: Any) -> Dict[str, Any]:
    """Reset pinned to (problem, goal) and end the exploration episode at once."""
    env.reset(options={"problem_id": problem_id, "instruction": [goal + 1]}, **reset_kwargs)
    obs, reward, terminated, _, info = env.step(END_EPISODE)
    assert info["episode_end"] and info["episode_phase"] == EXPLORATION and not terminated
    assert obs["phase"] == EXECUTION and pos(obs) == START
    return obs


class Walker(ScriptedAgent):
    """Ends exploration at once, then walks straight (x first) to the instructed goal."""

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        if obs["phase"] == EXPLORATION:
            return END_EPISODE
        x, y = pos(obs)
        gx, gy = GOALS[int(obs["instruction"][0]) - 1]
        if x != gx:
            return RIGHT if gx > x else LEFT
        return UP if gy > y else DOWN


# ---------------------------------------------------------------------------------------- dynamics
def test_moves_clip_at_the_border_and_other_actions_stay():
    env = make("vanilla")
    obs, _ = env.reset(seed=0)
    assert pos(obs) == START and obs["obs"][2] == 0
    steps = run(env, [LEFT] * 6)  # 4 moves to x=0, then clipped
    assert [pos(s[0]) for s in steps] == [(3, 4), (2, 4), (1, 4), (0, 4), (0, 4), (0, 4)]
    steps = run(env, [UP] * 5 + [RIGHT, DOWN])
    assert [pos(s[0]) for s in steps] == [(0, 5), (0, 6), (0, 7), (0, 8), (0, 8), (1, 8), (1, 7)]
    for a in (NOOP, RIDE, PICKUP, DROP):  # (1, 7) holds no bus: riding does nothing
        ((obs, *_),) = run(env, [a])
        assert pos(obs) == (1, 7)


@pytest.mark.parametrize("variant", VARIANTS)
def test_colored_buses_ride_both_ways(variant: str):
    env = make(variant, split="all")
    for problem_id in (0, 5, 23, env.n_problems - 1):
        perm = PERMUTATIONS[problem_id % 24]
        approach = {(4, 5): UP, (5, 4): RIGHT, (3, 4): LEFT, (4, 3): DOWN}
        for i, stop in enumerate(COLORED_STOPS):
            env.reset(options={"problem_id": problem_id})
            ((obs, *_),) = run(env, [approach[stop]])
            assert pos(obs) == stop and obs["obs"][2] == 1  # a bus is under the agent
            ((obs, *_),) = run(env, [RIDE])
            assert pos(obs) == COLORED_DESTINATIONS[perm[i]] and obs["obs"][2] == 1
            ((obs, *_),) = run(env, [RIDE])
            assert pos(obs) == stop


def test_gray_buses_lead_to_the_gray_permutation():
    env = make("distracting", split="all")
    problem_id = 7 + 24 * 13
    gray = PERMUTATIONS[13]
    assert env.routes(problem_id) == {
        **{s: COLORED_DESTINATIONS[d] for s, d in zip(COLORED_STOPS, PERMUTATIONS[7])},
        **{s: GRAY_DESTINATIONS[d] for s, d in zip(GRAY_STOPS, gray)},
    }
    approach = {(5, 5): [UP, RIGHT], (3, 3): [DOWN, LEFT], (3, 5): [UP, LEFT], (5, 3): [DOWN, RIGHT]}
    for i, stop in enumerate(GRAY_STOPS):
        env.reset(options={"problem_id": problem_id})
        obs = run(env, approach[stop])[-1][0]
        assert pos(obs) == stop and obs["obs"][2] == 1
        ((obs, *_),) = run(env, [RIDE])
        assert pos(obs) == GRAY_DESTINATIONS[gray[i]] and obs["obs"][2] == 1
        ((obs, *_),) = run(env, [RIDE])
        assert pos(obs) == stop
    # Without gray buses (map, vanilla) those cells hold nothing and riding there stays put.
    env = make("vanilla")
    env.reset(seed=0)
    steps = run(env, [UP, RIGHT, RIDE])
    assert [pos(s[0]) for s in steps] == [(4, 5), (5, 5), (5, 5)] and steps[-1][0]["obs"][2] == 0


def test_every_problem_is_a_distinct_pair_of_permutations():
    env = make("distracting", split="all")
    all_routes = {tuple(sorted(env.routes(p).items())) for p in range(576)}
    assert len(all_routes) == 576
    assert [PERMUTATIONS.index(p) for p in itertools.permutations(range(4))] == list(range(24))


def test_map_reveals_the_colored_permutation_only_on_the_map_cell():
    env = make("map")
    assert env.observation_space["obs"] == gym.spaces.MultiDiscrete([9, 9, 5, 25])
    for problem_id in (0, 13, 23):
        obs, _ = env.reset(options={"problem_id": problem_id})
        assert list(obs["obs"]) == [4, 4, 0, 0]
        steps = run(env, [RIGHT, RIGHT, RIGHT, DOWN, DOWN])
        assert [list(s[0]["obs"][2:]) for s in steps] == [[1, 0], [0, 0], [0, 0], [2, 1 + problem_id], [0, 0]]
        assert pos(steps[3][0]) == MAP_CELL


def test_shows_map_only_on_the_map_cell_of_the_map_variant():
    env = make("map")
    obs, _ = env.reset(options={"problem_id": 13})
    states = [obs["obs"]] + [s[0]["obs"] for s in run(env, [RIGHT, RIGHT, RIGHT, DOWN, DOWN])]
    assert [shows_map(s) for s in states] == [False, False, False, False, True, False]
    vanilla, _ = make("vanilla").reset(seed=0)
    assert not shows_map(vanilla["obs"])  # three dimensions: no map entry


def test_bus_stop_of_names_both_ends_of_each_route_by_its_stop():
    routes = make("vanilla").routes(5)
    stop_of = bus_stop_of(routes)
    assert set(stop_of) == set(routes) | set(routes.values())
    for stop, dest in routes.items():
        assert stop_of[stop] == stop_of[dest] == stop


def test_observation_spaces_are_fixed_per_variant():
    assert make("distracting").observation_space["obs"] == gym.spaces.MultiDiscrete([9, 9, 5])
    assert make("vanilla").observation_space["obs"] == gym.spaces.MultiDiscrete([9, 9, 5])
    for variant in VARIANTS:
        env = make(variant)
        assert env.action_space == gym.spaces.Discrete(9)
        assert env.observation_space["instruction"] == gym.spaces.MultiDiscrete([5])
        assert env.end_episode_action == END_EPISODE


# ----------------------------------------------------------------------------------------- rewards
def test_step_costs_goal_reward_and_termination():
    env = make("vanilla")
    start_execution(env, problem_id=0, goal=0)  # goal (0, 0)
    steps = run(env, [UP, NOOP, DOWN])  # other actions cost the same
    assert [s[1] for s in steps] == pytest.approx([-0.1] * 3)
    steps = run(env, [LEFT] * 4 + [DOWN] * 3)
    assert [s[1] for s in steps] == pytest.approx([-0.1] * 7)
    assert not any(s[3].get("episode_end") for s in steps)
    ((obs, reward, terminated, info),) = run(env, [DOWN])
    assert reward == pytest.approx(1.0)  # +1, not +0.9
    assert terminated and info["episode_end"] and info["episode_length"] == 11
    assert tuple(info["final_obs"][:2]) == (0, 0)
    assert info["execution_returns"] == pytest.approx([-1.0 + 1.0])


def test_other_corners_neither_reward_nor_end():
    env = make("vanilla")
    start_execution(env, problem_id=3, goal=1)  # goal (8, 8)
    steps = run(env, [LEFT] * 4 + [DOWN] * 4)  # reach (0, 0)
    assert pos(steps[-1][0]) == (0, 0)
    assert [s[1] for s in steps] == pytest.approx([-0.1] * 8)
    assert not any(s[3].get("episode_end") for s in steps)


@pytest.mark.parametrize("steps_before", [0, 3, 19])
def test_end_episode_costs_the_remaining_steps(steps_before: int):
    env = make("distracting")
    start_execution(env, problem_id=11, goal=2)
    run(env, [NOOP] * steps_before)
    ((_, reward, terminated, info),) = run(env, [END_EPISODE])
    assert reward == pytest.approx(-0.1 * (20 - steps_before))
    assert terminated and info["episode_length"] == steps_before + 1
    assert info["execution_returns"] == pytest.approx([-0.1 * steps_before - 0.1 * (20 - steps_before)])


@pytest.mark.parametrize("variant", VARIANTS)
def test_optimal_execution_is_0_8_and_walking_is_0_3(variant: str):
    env = make(variant, split="all")
    for problem_id in (0, 9, 23):
        routes = env.routes(problem_id)
        for goal in range(4):
            gx, gy = GOALS[goal]
            (stop,) = [s for s in COLORED_STOPS if abs(routes[s][0] - gx) + abs(routes[s][1] - gy) == 1]
            start_execution(env, problem_id, goal)
            first = {(4, 5): UP, (5, 4): RIGHT, (3, 4): LEFT, (4, 3): DOWN}[stop]
            obs = run(env, [first, RIDE])[-1][0]
            dx, dy = gx - pos(obs)[0], gy - pos(obs)[1]
            last = {(-1, 0): LEFT, (1, 0): RIGHT, (0, 1): UP, (0, -1): DOWN}[(dx, dy)]
            ((_, _, terminated, info),) = run(env, [last])
            assert terminated and info["execution_returns"] == pytest.approx([0.8])
            result = play_trial(env, Walker(), options={"problem_id": problem_id, "instruction": [goal + 1]})
            assert result["execution_returns"] == pytest.approx([0.3])


# ------------------------------------------------------------------------------------------ splits
def test_splits():
    env = make("distracting")
    train, test, everything = (env.problem_ids(s) for s in ("train", "test", "all"))
    assert len(train) == 53 and len(test) == 523 and len(everything) == 576 and env.n_problems == 576
    assert list(train) == list(range(0, 576, 11))
    assert not set(train) & set(test) and sorted(set(train) | set(test)) == list(everything)
    for variant in ("map", "vanilla"):
        env = make(variant)
        assert env.n_problems == 24
        for split in ("train", "test", "all"):
            assert list(env.problem_ids(split)) == list(range(24))


@pytest.mark.parametrize("split", ["train", "test"])
def test_sampled_problems_stay_in_their_split(split: str):
    env = make("distracting", split=split)
    ids = {env.reset(seed=s)[1]["problem_id"] for s in range(60)}
    allowed = set(env.problem_ids(split))
    assert ids <= allowed and len(ids) > 10


# -------------------------------------------------------------------------------- trial structure
@pytest.mark.parametrize("variant", VARIANTS)
def test_inner_episodes_last_the_horizon(variant: str):
    env = make(variant, n_exec_episodes=2)
    env.reset(seed=1)
    lengths, terminated, t = [], False, 0
    while not terminated:
        _, _, terminated, _, info = env.step(NOOP)
        t += 1
        if info.get("episode_end"):
            lengths.append(info["episode_length"])
    assert lengths == [20, 20, 20] and t == 60
    assert info["execution_returns"] == pytest.approx([-2.0, -2.0])
    env = make(variant, horizon=7)
    env.reset(seed=1)
    steps = run(env, [NOOP] * 7)
    assert steps[-1][3]["episode_end"] and steps[-1][3]["episode_length"] == 7


def test_reward_free_exploration():
    env = make("distracting")
    obs, info = env.reset(options={"problem_id": 0, "instruction": [1]})
    assert obs["phase"] == EXPLORATION and list(obs["instruction"]) == [0]
    # Walk to the (0, 0) corner, ride, end: nothing rewards, the corner does not end the episode.
    steps = run(env, [LEFT] * 4 + [DOWN] * 4 + [NOOP, UP, RIDE])
    assert pos(steps[7][0]) == (0, 0)
    for obs, reward, terminated, info in steps:
        assert reward == 0.0 and not terminated and not info.get("episode_end")
        assert list(obs["instruction"]) == [0] and obs["prev_reward"][0] == 0.0
    ((obs, reward, _, info),) = run(env, [END_EPISODE])  # free while exploring
    assert reward == 0.0 and info["episode_end"] and info["episode_return"] == 0.0
    assert obs["phase"] == EXECUTION and list(obs["instruction"]) == [1]


def test_rewarded_exploration_option():
    env = make("vanilla", reward_free_exploration=False)
    obs, _ = env.reset(options={"problem_id": 0, "instruction": [1]})
    assert obs["phase"] == EXPLORATION and list(obs["instruction"]) == [1]
    steps = run(env, [LEFT] * 4 + [DOWN] * 4)
    assert steps[0][1] == pytest.approx(-0.1) and steps[-1][1] == pytest.approx(1.0)
    assert steps[-1][3]["episode_end"] and steps[-1][3]["episode_phase"] == EXPLORATION


@pytest.mark.parametrize("variant", VARIANTS)
def test_no_problem_id_in_observations(variant: str):
    env = make(variant, split="all")
    first = [env.reset(options={"problem_id": p})[0] for p in range(0, env.n_problems, 5)]
    for obs in first[1:]:
        for key in obs:
            np.testing.assert_array_equal(obs[key], first[0][key])
    # Over random trials, no observed value tracks the problem ID.
    env = make(variant, split="all", n_exec_episodes=2)
    agent = RandomAgent(env.action_space, seed=0)
    matches: Dict[tuple, List[bool]] = {}
    for seed in range(30):
        obs, info = env.reset(seed=seed)
        terminated = False
        while not terminated:
            for key, value in obs.items():
                for j, v in enumerate(np.ravel(value)):
                    matches.setdefault((key, j), []).append(float(v) == info["problem_id"])
            obs, _, terminated, _, info = env.step(agent.act(obs, public_info(info)))
    assert set(k for k, _ in matches) == set(env.observation_space.spaces)
    assert max(np.mean(m) for m in matches.values()) < 0.2


# ------------------------------------------------------------------------------------------ oracle
@pytest.mark.parametrize("variant", ["map", "vanilla"])
def test_oracle_is_optimal_on_every_problem_and_instruction(variant: str):
    env = make(variant, split="all")
    oracle = make_oracle(env)
    for problem_id in range(24):
        for k in range(1, 5):
            result = play_trial(env, oracle, options={"problem_id": problem_id, "instruction": [k]})
            assert result["execution_returns"] == pytest.approx([0.8])
            assert result["exploration_length"] == (5 if variant == "map" else 11)


def test_oracle_is_optimal_on_distracting_bus():
    env = make("distracting", split="all", n_exec_episodes=2)
    oracle = make_oracle(env)
    rng = np.random.default_rng(0)
    for problem_id in [0, 575, *rng.choice(576, size=40, replace=False)]:
        for k in range(1, 5):
            result = play_trial(env, oracle, options={"problem_id": int(problem_id), "instruction": [k]})
            assert result["execution_returns"] == pytest.approx([0.8, 0.8])
    # Unpinned trials (sampled problems and instructions, test split) too.
    env = gym.make("MetaBus-v0", split="test", n_exec_episodes=3)
    for seed in range(10):
        assert play_trial(env, make_oracle(env), seed=seed)["execution_returns"] == pytest.approx([0.8] * 3)


def test_oracle_reads_a_ride_on_the_last_exploration_step_from_final_obs():
    # With horizon 10 the third ride is the exploration episode's last step: its destination is
    # only in info["final_obs"].
    env = make("vanilla", split="all", horizon=10)
    oracle = make_oracle(env)
    for problem_id in range(0, 24, 5):
        for k in range(1, 5):
            result = play_trial(env, oracle, options={"problem_id": problem_id, "instruction": [k]})
            assert result["exploration_length"] == 10 and result["execution_returns"] == pytest.approx([0.8])


def test_oracle_needs_its_exploration():
    """The oracle's return comes from what it explored: with no time to explore, it walks (0.3)."""
    env = make("vanilla", split="all", horizon=20)
    oracle = make_oracle(env)

    class SkipExploration(ScriptedAgent):
        def reset(self) -> None:
            oracle.reset()

        def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
            return END_EPISODE if obs["phase"] == EXPLORATION else oracle.act(obs, info)

    for problem_id in (0, 17):
        result = play_trial(env, SkipExploration(), options={"problem_id": problem_id, "instruction": [2]})
        assert result["execution_returns"] == pytest.approx([0.3])


class ScriptedExplorer(ScriptedAgent):
    """Plays ``plan`` while exploring (then ends the episode); while executing it rides the colored
    bus at (3, 4), which no plan below rides while exploring."""

    def __init__(self, plan: Sequence[int]) -> None:
        self.plan = plan

    def reset(self) -> None:
        self.k = 0

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        if int(obs["phase"]) != EXPLORATION:
            return {START: LEFT, (3, 4): RIDE}.get(pos(obs), UP)
        self.k += 1
        return self.plan[self.k - 1] if self.k <= len(self.plan) else END_EPISODE


def test_exploration_report_of_the_oracle_matches_figure_7():
    distracting = exploration_report(gym.make("MetaBus-v0", split="test"), make_oracle(make()), n_trials=12)
    assert distracting.colored_routes.tolist() == [3] * 12  # rides 3 of the 4 colored buses
    assert distracting.gray_routes.tolist() == [0] * 12 and not distracting.read_map.any()
    assert distracting.exploration_lengths.tolist() == [11] * 12  # 10 steps, then end the episode
    assert distracting.execution_returns == pytest.approx([0.8] * 12)
    on_map = exploration_report(gym.make("MetaBus-v0", variant="map"), make_oracle(make("map")), n_trials=5)
    assert on_map.read_map.all() and on_map.colored_routes.tolist() == [0] * 5
    assert on_map.exploration_lengths.tolist() == [5] * 5
    assert distracting.summary() == (
        "colored routes seen 3.00 (trials with 0..4: [0, 0, 0, 12, 0]), gray routes 0.00, "
        "exploration length 11.0, execution return 0.800, goal missed in 0.0% of execution episodes; "
        "execution return by colored routes seen: 3: 0.800 (12 trials)"
    )
    assert "map read 100%, exploration length 5.0" in on_map.summary() and "gray" not in on_map.summary()


def test_exploration_report_gives_the_execution_return_for_each_coverage():
    report = BusExplorationReport(
        colored_routes=np.array([2, 3, 2, 4, 3]),
        gray_routes=np.zeros(5, dtype=int),
        read_map=np.zeros(5, dtype=bool),
        exploration_lengths=np.full(5, 20),
        execution_returns=np.array([-2.0, 0.8, 0.8, 0.8, 0.3]),
    )
    by_routes = report.returns_by_colored_routes()
    assert list(by_routes) == [2, 3, 4]
    assert by_routes[2] == (2, pytest.approx(-0.6)) and by_routes[3] == (2, pytest.approx(0.55))
    assert by_routes[4] == (1, pytest.approx(0.8))
    assert report.summary().endswith(
        "by colored routes seen: 2: -0.600 (2 trials); 3: 0.550 (2 trials); 4: 0.800 (1 trials)"
    )

    # An agent that never moves misses every goal: each execution episode returns -0.1 x horizon.
    class Idle(ScriptedAgent):
        def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
            return END_EPISODE if int(obs["phase"]) == EXPLORATION else NOOP

    idle = exploration_report(gym.make("MetaBus-v0", horizon=5, n_exec_episodes=2), Idle(), 3)
    assert idle.goal_missed is not None and idle.goal_missed.tolist() == [1.0] * 3
    assert idle.execution_returns == pytest.approx([-0.5] * 3)
    assert "goal missed in 100.0% of execution episodes" in idle.summary()


def test_exploration_report_counts_each_route_once_from_either_end():
    # Onto the gray stop (5, 5), ride there and back (one gray route), RIDE off any bus (nothing),
    # onto the colored stop (4, 5), ride; the execution episode's ride at (3, 4) counts for nothing.
    plan = [RIGHT, UP, RIDE, RIDE, RIGHT, RIDE, LEFT, LEFT, RIDE]
    env = gym.make("MetaBus-v0", split="all")
    report = exploration_report(env, ScriptedExplorer(plan), n_trials=4, problem_ids=[0, 24 * 7 + 3])
    assert report.colored_routes.tolist() == [1] * 4 and report.gray_routes.tolist() == [1] * 4
    assert report.exploration_lengths.tolist() == [len(plan) + 1] * 4
    nothing = exploration_report(env, ScriptedExplorer([RIDE]), n_trials=2)  # at the start: no bus
    assert nothing.colored_routes.tolist() == [0, 0] and nothing.gray_routes.tolist() == [0, 0]
    with pytest.raises(ValueError, match="MetaBus-v0"):
        exploration_report(gym.make("MetaBandit-v0"), ScriptedExplorer([]), n_trials=1)
    with pytest.raises(ValueError, match="n_trials"):
        exploration_report(env, ScriptedExplorer([]), n_trials=0)
    with pytest.raises(ValueError, match="problem_ids must not be empty"):
        exploration_report(env, ScriptedExplorer([]), n_trials=1, problem_ids=[])


# ---------------------------------------------------------------------------------- reproducibility
def trajectory(env: MetaBusEnv, seed: int) -> list:
    obs, info = env.reset(seed=seed)
    agent = RandomAgent(env.action_space, seed=seed)
    out, terminated = [(info["problem_id"], tuple(obs["obs"]))], False
    while not terminated:
        obs, reward, terminated, _, info = env.step(agent.act(obs, public_info(info)))
        out.append((tuple(obs["obs"]), tuple(obs["instruction"]), reward))
    return out


def test_seeding_reproduces_problem_instruction_and_trajectory():
    a, b = make("distracting", n_exec_episodes=3), make("distracting", n_exec_episodes=3)
    assert trajectory(a, 123) == trajectory(b, 123)
    runs = [trajectory(a, s) for s in range(6)]
    assert len({r[0][0] for r in runs}) > 1  # different seeds, different problems
    # Instructions drawn per execution episode are reproducible too (and vary).
    instructions = set()
    for seed in range(5):
        for env in (a, b):
            env.reset(seed=seed)
        for env in (a, b):
            env.step(END_EPISODE)
        ia = [tuple(a.step(END_EPISODE)[0]["instruction"]) for _ in range(2)]
        ib = [tuple(b.step(END_EPISODE)[0]["instruction"]) for _ in range(2)]
        assert ia == ib
        instructions.update(ia)
    assert len(instructions) > 1


def test_pinned_problem_and_instruction_hold_for_every_execution_episode():
    env = make("distracting", split="train", n_exec_episodes=3)
    for seed, problem_id, k in [(0, 100, 3), (1, 575, 1), (2, 100, 4)]:  # pinning may leave the split
        obs, info = env.reset(seed=seed, options={"problem_id": problem_id, "instruction": [k]})
        assert info["problem_id"] == problem_id
        seen, terminated = [], False
        while not terminated:
            obs, _, terminated, _, info = env.step(END_EPISODE)
            assert info["problem_id"] == problem_id
            if not terminated:
                seen.append(int(obs["instruction"][0]))
        assert seen == [k, k, k]


# ------------------------------------------------------------------------------------ env checkers
@pytest.mark.parametrize("variant", VARIANTS)
def test_gymnasium_and_sb3_env_checkers(variant: str):
    env = gym.make("MetaBus-v0", variant=variant, render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    sb3_check_env(MetaBusEnv(variant=variant), warn=True)


# -------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"variant": "rainbow"}, "variant.*distracting.*map.*vanilla"),
        ({"split": "validation"}, "split.*train.*test.*all"),
        ({"horizon": 0}, "horizon"),
        ({"n_exec_episodes": 0}, "n_exec_episodes"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_bad_constructor_arguments(kwargs: Dict[str, Any], match: str):
    with pytest.raises(ValueError, match=match):
        MetaBusEnv(**kwargs)


@pytest.mark.parametrize(
    "variant, problem_id", [("distracting", 576), ("distracting", -1), ("map", 24), ("vanilla", 1.5), ("map", True)]
)
def test_bad_pinned_problem(variant: str, problem_id: Any):
    env = make(variant)
    with pytest.raises(ValueError, match="problem_id"):
        env.reset(options={"problem_id": problem_id})
    with pytest.raises(ValueError, match="problem_id"):
        env.routes(problem_id)


@pytest.mark.parametrize("instruction", [[0], [5], [1, 2], 3])
def test_bad_pinned_instruction(instruction: Any):
    with pytest.raises(ValueError, match="instruction"):
        make("vanilla").reset(options={"instruction": instruction})


def test_bad_action():
    env = make("vanilla")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(9)


# ----------------------------------------------------------------------------------------- render
@pytest.mark.parametrize("variant", VARIANTS)
def test_render(variant: str):
    env = gym.make("MetaBus-v0", variant=variant, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8 and frame.shape[0] > 400
    env.step(UP)
    moved = env.render()
    assert moved.shape == frame.shape and np.any(moved != frame)  # the agent is drawn where it is
    no_render = MetaBusEnv(variant=variant)
    no_render.reset(seed=0)
    assert no_render.render() is None


def test_discovery_rewards_sort_exploration_steps_by_what_they_found():
    def trajectory(env: MetaBusEnv, problem_id: int, actions: Sequence[int]):
        obs, _ = env.reset(options={"problem_id": problem_id})
        states = [obs["obs"]] + [step[0]["obs"] for step in run(env, actions)]
        return np.array(states), np.array(actions)

    # Distracting bus: up, right to a gray stop, ride there and back, left to a colored stop, ride.
    env = make("distracting", split="all")
    problem_id = 7 + 24 * 13
    actions = [UP, RIGHT, RIDE, RIDE, LEFT, RIDE, NOOP]
    rewards = np.arange(len(actions), dtype=float)
    found = discovery_rewards(env, [trajectory(env, problem_id, actions)], [rewards], [problem_id])
    assert list(found) == ["colored route", "gray route", "route again", "other"]
    assert found["gray route"].tolist() == [2.0] and found["route again"].tolist() == [3.0]
    assert found["colored route"].tolist() == [5.0] and found["other"].tolist() == [0.0, 1.0, 4.0, 6.0]
    # Map: three steps right and one down reach the map; staying on it finds nothing more.
    env = make("map")
    actions = [RIGHT, RIGHT, RIGHT, DOWN, NOOP]
    found = discovery_rewards(env, [trajectory(env, 5, actions)], [np.arange(5.0)], [5])
    assert found == {"map": pytest.approx([3.0]), "other": pytest.approx([0.0, 1.0, 2.0, 4.0])}
    with pytest.raises(ValueError, match="MetaBus-v0"):
        discovery_rewards(gym.make("MetaBandit-v0"), [], [], [])
