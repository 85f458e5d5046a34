"""MetaCook-v0: kitchen dynamics, the shaped reward's stage machine, splits, oracle optimality."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest

import dream_envs
from dream_envs import EXECUTION, EXPLORATION, RandomAgent, ScriptedAgent, play_trial, public_info
from dream_envs.cook import (
    DOWN,
    DROP,
    END_EPISODE,
    FRIDGE,
    HELD_OUT_INSTRUCTIONS,
    HELD_OUT_PROBLEMS,
    LEFT,
    NO_OBJECT,
    NOOP,
    PICKUP,
    POT,
    RIDE_BUS,
    RIGHT,
    RUINED,
    START,
    UP,
    CookReport,
    MetaCookEnv,
    behaviour_report,
    cook_transition,
    first_openings,
    fridge_contents,
    opening_rewards,
    optimal_execution_return,
    problem_id_of,
    recipe_stage,
    valid_instructions,
)
from dream_envs.cook.report import _replay_execution

# Problem 290 holds (4, 7, 6): fridge 0 at (2, 0) has 4, fridge 1 at (2, 1) has 7, fridge 2 at (2, 2) has 6.
PROBLEM = problem_id_of((4, 7, 6))
START_OBS = [1, 1, POT, 0, 0, 0]


def make(**kwargs) -> MetaCookEnv:
    return MetaCookEnv(**kwargs)


def to_execution(env: MetaCookEnv, problem_id: int = PROBLEM, instruction=(7, 6), **reset_kwargs):
    """Reset with a pinned trial and end the (reward-free) exploration at once."""
    env.reset(seed=0, options={"problem_id": problem_id, "instruction": list(instruction)}, **reset_kwargs)
    obs, reward, terminated, _, info = env.step(END_EPISODE)
    assert reward == 0.0 and not terminated and info["phase"] == EXECUTION
    return obs


def run(env: MetaCookEnv, actions):
    """Step through ``actions``; return the rewards and the last step's outputs."""
    rewards, out = [], None
    for a in actions:
        out = env.step(a)
        rewards.append(out[1])
    return rewards, out


# ---------------------------------------------------------------------------------------- problems


def test_problem_id_base7_mapping():
    assert fridge_contents(0) == (1, 1, 1)
    assert fridge_contents(1) == (2, 1, 1)  # least significant digit: fridge 0
    assert fridge_contents(7) == (1, 2, 1)
    assert fridge_contents(49) == (1, 1, 2)
    assert fridge_contents(342) == (7, 7, 7)
    assert [problem_id_of(fridge_contents(k)) for k in range(343)] == list(range(343))
    assert len({fridge_contents(k) for k in range(343)}) == 343
    with pytest.raises(ValueError, match="contents"):
        problem_id_of((0, 1, 2))


def test_valid_instructions_are_pairs_of_present_ingredients():
    assert valid_instructions(problem_id_of((3, 3, 3))) == [(3, 3)]
    assert valid_instructions(problem_id_of((5, 2, 5))) == [(2, 2), (2, 5), (5, 2), (5, 5)]
    assert len(valid_instructions(PROBLEM)) == 9


# ---------------------------------------------------------------------------------------- spaces, observation


def test_spaces_and_first_observation_hides_problem():
    env = make()
    assert env.action_space == gym.spaces.Discrete(9)
    assert list(env.observation_space["obs"].nvec) == [3, 3, 5, 8, 8, 8]
    assert list(env.observation_space["instruction"].nvec) == [8, 8]
    assert env.n_problems == 343
    first = []
    for k in (0, 100, PROBLEM, 342):
        obs, info = env.reset(options={"problem_id": k})
        assert info["problem_id"] == k
        assert obs["obs"].tolist() == START_OBS
        assert obs["instruction"].tolist() == [0, 0]
        first.append({key: np.asarray(v).tolist() for key, v in obs.items()})
    assert all(f == first[0] for f in first)
    # Moving without picking up reveals nothing either: two problems, same observations.
    seqs = []
    for k in (problem_id_of((1, 2, 3)), problem_id_of((7, 6, 5))):
        env.reset(options={"problem_id": k})
        seqs.append([env.step(a)[0]["obs"].tolist() for a in (RIGHT, UP, DOWN, DOWN, LEFT, DROP)])
    assert seqs[0] == seqs[1]


# ---------------------------------------------------------------------------------------- dynamics


def test_moves_clip_at_border_and_object_codes():
    env = make()
    env.reset(seed=0)
    obs = [env.step(a)[0]["obs"].tolist() for a in (LEFT, LEFT, DOWN, DOWN, RIGHT, RIGHT, RIGHT, UP, UP, UP)]
    assert [o[:3] for o in obs] == [
        [0, 1, NO_OBJECT],
        [0, 1, NO_OBJECT],  # x clipped at 0
        [0, 0, NO_OBJECT],
        [0, 0, NO_OBJECT],  # y clipped at 0
        [1, 0, NO_OBJECT],
        [2, 0, FRIDGE],
        [2, 0, FRIDGE],  # x clipped at 2
        [2, 1, FRIDGE],
        [2, 2, FRIDGE],
        [2, 2, FRIDGE],  # y clipped at 2
    ]
    env.reset(seed=0)
    for a in (NOOP, RIDE_BUS, PICKUP, DROP):  # at the pot, empty-handed: nothing changes
        assert env.step(a)[0]["obs"].tolist() == START_OBS


def test_pickup_drop_and_pot():
    env = make(horizon=50)
    env.reset(seed=0, options={"problem_id": PROBLEM})
    step = lambda a: env.step(a)[0]["obs"].tolist()  # noqa: E731
    assert step(RIGHT) == [2, 1, FRIDGE, 0, 0, 0]
    assert step(PICKUP) == [2, 1, FRIDGE, 7, 0, 0]  # the content shows as the inventory
    assert step(DOWN) == [2, 0, FRIDGE, 7, 0, 0]
    assert step(PICKUP) == [2, 0, FRIDGE, 4, 0, 0]  # full inventory: the fridge's ingredient replaces it
    assert step(LEFT) == [1, 0, NO_OBJECT, 4, 0, 0]
    assert step(DROP) == [1, 0, NO_OBJECT, 0, 0, 0]  # away from the pot: discarded
    assert step(PICKUP) == [1, 0, NO_OBJECT, 0, 0, 0]  # no fridge here
    for a in (RIGHT, PICKUP, LEFT, UP):
        step(a)
    assert step(DROP) == [1, 1, POT, 0, 4, 0]  # first slot
    for a in (RIGHT, UP, PICKUP, DOWN, LEFT):
        step(a)
    assert step(DROP) == [1, 1, POT, 0, 4, 6]  # second slot
    for a in (RIGHT, PICKUP, LEFT):
        step(a)
    assert step(DROP) == [1, 1, POT, 7, 4, 6]  # a full pot takes nothing


def test_each_episode_starts_fresh():
    env = make(n_exec_episodes=2)
    env.reset(seed=0, options={"problem_id": PROBLEM, "instruction": [7, 7]})
    run(env, [RIGHT, PICKUP, LEFT, DROP, RIGHT, PICKUP])  # exploration: pot (7, 0), holding 7
    obs, _, _, _, info = env.step(END_EPISODE)
    assert info["final_obs"].tolist() == [2, 1, FRIDGE, 7, 7, 0]
    assert obs["obs"].tolist() == START_OBS and obs["episode_start"] == 1
    run(env, [RIGHT, PICKUP])
    obs, _, _, _, info = env.step(END_EPISODE)
    assert info["episode_index"] == 2 and obs["obs"].tolist() == START_OBS


# ---------------------------------------------------------------------------------------- rewards


def test_recipe_stage_machine():
    a, b = 4, 6
    assert recipe_stage(0, (0, 0), (a, b)) == 0
    assert recipe_stage(6, (0, 0), (a, b)) == 0
    assert recipe_stage(4, (0, 0), (a, b)) == 1
    assert recipe_stage(0, (4, 0), (a, b)) == 2
    assert recipe_stage(4, (4, 0), (a, b)) == 2
    assert recipe_stage(6, (4, 0), (a, b)) == 3
    assert recipe_stage(0, (4, 6), (a, b)) == 4
    assert recipe_stage(0, (6, 0), (a, b)) == RUINED
    assert recipe_stage(4, (6, 4), (a, b)) == RUINED
    assert recipe_stage(6, (4, 4), (a, b)) == RUINED
    # A recipe with the same ingredient twice.
    assert [recipe_stage(i, p, (7, 7)) for i, p in [(7, (0, 0)), (0, (7, 0)), (7, (7, 0)), (0, (7, 7))]] == [1, 2, 3, 4]


def test_shaped_reward_progress_and_completion():
    env = make()
    to_execution(env, instruction=(4, 6))  # 4 in fridge 0 at (2, 0), 6 in fridge 2 at (2, 2)
    actions = [RIGHT, DOWN, PICKUP, LEFT, UP, DROP, RIGHT, UP, PICKUP, LEFT, DOWN]
    rewards, _ = run(env, actions)
    assert rewards == pytest.approx([-0.1, -0.1, 0.25, -0.1, -0.1, 0.25, -0.1, -0.1, 0.25, -0.1, -0.1])
    assert env.stage == 3
    obs, reward, terminated, truncated, info = env.step(DROP)
    assert reward == pytest.approx(0.25) and terminated and not truncated  # stage 4 ends the episode (and trial)
    assert info["episode_end"] and info["episode_length"] == 12
    assert info["final_obs"].tolist() == [1, 1, POT, 0, 4, 6]
    assert info["execution_returns"] == [pytest.approx(0.2)]
    assert optimal_execution_return(PROBLEM, (4, 6)) == pytest.approx(0.2)


def test_undo_penalties_return_to_earlier_stage():
    env = make(horizon=50)
    to_execution(env, instruction=(7, 6))
    rewards, _ = run(env, [RIGHT, PICKUP, PICKUP])
    assert rewards == pytest.approx([-0.1, 0.25, -0.1])  # picking A again earns nothing: no gaming
    assert env.stage == 1
    assert env.step(DROP)[1] == pytest.approx(-0.35) and env.stage == 0  # dropped away from the pot: -0.1 - 0.25
    assert env.step(PICKUP)[1] == pytest.approx(0.25) and env.stage == 1
    env.step(UP)
    assert env.step(PICKUP)[1] == pytest.approx(-0.35) and env.stage == 0  # wrong one picked over A
    rewards, _ = run(env, [DOWN, PICKUP, LEFT, DROP, RIGHT, UP, PICKUP])
    assert rewards == pytest.approx([-0.1, 0.25, -0.1, 0.25, -0.1, -0.1, 0.25]) and env.stage == 3
    assert env.step(DOWN)[1] == pytest.approx(-0.1)
    assert env.step(PICKUP)[1] == pytest.approx(-0.35) and env.stage == 2  # 7 picked over B
    assert env.step(DROP)[1] == pytest.approx(-0.1) and env.stage == 2  # a non-needed ingredient: no change
    rewards, (_, _, terminated, _, _) = run(env, [UP, PICKUP, DOWN, LEFT, DROP])
    assert rewards == pytest.approx([-0.1, 0.25, -0.1, -0.1, 0.25]) and terminated


def test_ruined_dish_is_a_sink():
    env = make()
    to_execution(env, instruction=(7, 6))
    run(env, [RIGHT, PICKUP, LEFT])
    assert env.step(DROP)[1] == pytest.approx(0.25) and env.stage == 2
    run(env, [RIGHT, DOWN, PICKUP, UP, LEFT])  # holding 4, not the recipe's second ingredient
    assert env.step(DROP)[1] == pytest.approx(-0.35) and env.stage == RUINED
    rewards, (obs, _, terminated, _, info) = run(env, [RIGHT, UP, PICKUP, DOWN, LEFT, DROP])
    assert rewards == pytest.approx([-0.1] * 6) and not terminated  # holding 6 over a full pot: nothing to earn
    assert obs["obs"].tolist() == [1, 1, POT, 6, 7, 4]
    # A wrong first ingredient ruins the dish too.
    to_execution(env, instruction=(7, 6))
    run(env, [RIGHT, UP, PICKUP, DOWN, LEFT])
    assert env.step(DROP)[1] == pytest.approx(-0.35) and env.stage == RUINED


def test_undo_reward_option_and_why_the_default_adds_the_step_penalty():
    # Advancing then undoing must cost something beyond idling's share, or a loop is free.
    for undo_reward, pair in ((None, -0.1), (-0.25, 0.0)):
        env = make(horizon=50) if undo_reward is None else make(horizon=50, undo_reward=undo_reward)
        to_execution(env, instruction=(7, 6))
        run(env, [RIGHT])
        rewards, _ = run(env, [PICKUP, DROP])
        assert sum(rewards) == pytest.approx(pair) and env.stage == 0
    for bad in (0.5, -1.5, float("nan"), "-0.25", None, True, np.float32(0.5)):
        with pytest.raises(ValueError, match="undo_reward"):
            make(undo_reward=bad)
    # numpy scalars are numbers too, and are stored as a Python float
    for good in (np.float32(-0.3), np.int64(-1), -1):
        env = make(undo_reward=good)
        assert type(env.undo_reward) is float and env.undo_reward == pytest.approx(float(good))


def test_end_episode_costs_the_remaining_steps():
    env = make(horizon=20)
    to_execution(env)
    run(env, [RIGHT, PICKUP, NOOP])  # 3 steps taken, 17 left
    _, reward, terminated, _, info = env.step(END_EPISODE)
    assert reward == pytest.approx(-1.7) and terminated
    assert info["execution_returns"] == [pytest.approx(-0.1 + 0.25 - 0.1 - 1.7)]
    assert env.observation_space["prev_reward"].contains(np.array([reward], np.float32))


def test_horizon_and_reward_free_exploration():
    env = make(horizon=5, n_exec_episodes=2)
    obs, info = env.reset(seed=1, options={"problem_id": PROBLEM, "instruction": [7, 6]})
    assert env.instruction is None
    # Reward-free: a complete recipe in exploration earns nothing and does not end the episode.
    for t, a in enumerate([RIGHT, PICKUP, LEFT, DROP]):
        obs, reward, terminated, _, info = env.step(a)
        assert reward == 0.0 and not info.get("episode_end") and obs["prev_reward"][0] == 0.0
        assert obs["instruction"].tolist() == [0, 0] and obs["phase"] == EXPLORATION
    assert obs["obs"].tolist() == [1, 1, POT, 0, 7, 0]
    obs, reward, terminated, _, info = env.step(NOOP)
    assert info["episode_end"] and info["episode_length"] == 5 and info["episode_phase"] == EXPLORATION
    assert obs["phase"] == EXECUTION and obs["instruction"].tolist() == [7, 6] and obs["obs"].tolist() == START_OBS
    for _ in range(2):  # two execution episodes cut by the horizon
        rewards, (_, _, terminated, _, info) = run(env, [NOOP] * 5)
        assert rewards == pytest.approx([-0.1] * 5) and info["episode_end"] and info["episode_length"] == 5
    assert terminated and info["execution_returns"] == pytest.approx([-0.5, -0.5])


def test_exploration_with_rewards_variant():
    env = make(reward_free_exploration=False)
    obs, _ = env.reset(seed=0, options={"problem_id": PROBLEM, "instruction": [7, 7]})
    assert obs["instruction"].tolist() == [7, 7]
    rewards, (_, _, terminated, _, info) = run(env, [RIGHT, PICKUP, LEFT, DROP, RIGHT, PICKUP, LEFT, DROP])
    assert sum(rewards) == pytest.approx(0.6) and info["episode_end"] and info["episode_phase"] == EXPLORATION
    assert not terminated and info["phase"] == EXECUTION


# ---------------------------------------------------------------------------------------- splits


def test_split_sizes_and_disjointness():
    env = make()
    train, test, all_ = (set(env.problem_ids(s).tolist()) for s in ("train", "test", "all"))
    assert len(HELD_OUT_PROBLEMS) == round(0.01 * 343) == 3
    assert HELD_OUT_PROBLEMS == tuple(sorted(np.random.default_rng(0).choice(343, 3, replace=False).tolist()))
    assert (len(train), len(test), len(all_)) == (340, 109, 343)
    assert all_ == set(range(343)) and train == all_ - set(HELD_OUT_PROBLEMS)
    assert set(HELD_OUT_PROBLEMS) <= test
    held = set(HELD_OUT_INSTRUCTIONS)
    train_pairs = {(k, i) for k in train for i in env.instructions(k, "train")}
    test_pairs = {(k, i) for k in test for i in env.instructions(k, "test")}
    all_pairs = {(k, i) for k in range(343) for i in valid_instructions(k)}
    assert (len(train_pairs), len(test_pairs), len(all_pairs)) == (2268, 133, 2401)
    assert not train_pairs & test_pairs and train_pairs | test_pairs == all_pairs
    assert all(i not in held for _, i in train_pairs)
    # Every test trial is held out by its problem or its instruction; every test problem has some.
    assert all(k in HELD_OUT_PROBLEMS or i in held for k, i in test_pairs)
    assert all(env.instructions(k, "test") for k in test)
    assert env.instructions(0, "test") == []  # (1, 1, 1) holds no held-out recipe
    with pytest.raises(ValueError, match="split"):
        env.instructions(0, "valid")


def test_the_held_out_split_parts_tell_an_unseen_kitchen_from_an_unseen_recipe():
    env = make()
    held = set(HELD_OUT_INSTRUCTIONS)
    pairs = {s: {(k, i) for k in env.problem_ids(s) for i in env.instructions(k, s)} for s in env.splits}
    assert env.splits == ("train", "test", "all", "test_problems", "test_instructions")
    assert (len(pairs["test_problems"]), len(pairs["test_instructions"])) == (25, 106)
    # An unseen kitchen with training recipes; an unseen recipe in a training kitchen.
    assert all(k in HELD_OUT_PROBLEMS and i not in held for k, i in pairs["test_problems"])
    assert all(k not in HELD_OUT_PROBLEMS and i in held for k, i in pairs["test_instructions"])
    assert set(env.problem_ids("test_problems").tolist()) == set(HELD_OUT_PROBLEMS)
    # "test" is the two parts and the pairs held out both ways, here (1, 5, 4) and (1, 4, 5) with (5, 4).
    both = pairs["test"] - pairs["test_problems"] - pairs["test_instructions"]
    assert both == {(175, (5, 4)), (217, (5, 4))}
    assert pairs["test_problems"] | pairs["test_instructions"] <= pairs["test"]
    assert not pairs["test_problems"] & pairs["test_instructions"]
    # A made env samples only from its part (the oracle's exact mean there is 0.328).
    env = make(split="test_problems")
    env.reset(seed=1)
    for _ in range(200):
        _, info = env.reset()
        obs = env.step(END_EPISODE)[0]
        assert (info["problem_id"], tuple(obs["instruction"].tolist())) in pairs["test_problems"]


@pytest.mark.parametrize("split", ["train", "test"])
def test_sampling_respects_the_split(split):
    env = make(split=split)
    held = set(HELD_OUT_INSTRUCTIONS)
    env.reset(seed=123)
    seen_problems, seen_instructions = set(), set()
    for _ in range(1500):
        _, info = env.reset()
        obs = env.step(END_EPISODE)[0]
        k, i = info["problem_id"], tuple(obs["instruction"].tolist())
        assert i in valid_instructions(k)
        if split == "train":
            assert k not in HELD_OUT_PROBLEMS and i not in held
        else:
            assert k in HELD_OUT_PROBLEMS or i in held
        seen_problems.add(k)
        seen_instructions.add(i)
    if split == "test":
        assert seen_instructions >= held and set(HELD_OUT_PROBLEMS) <= seen_problems
    else:
        assert len(seen_problems) > 300


def test_problem_pinned_outside_split_falls_back_to_its_recipes():
    env = make(split="test", n_exec_episodes=5)
    env.reset(seed=0, options={"problem_id": 0})  # (1, 1, 1): no held-out recipe
    obs = env.step(END_EPISODE)[0]
    assert obs["instruction"].tolist() == [1, 1]


# ---------------------------------------------------------------------------------------- pinning, seeding, errors


def test_pinned_problem_and_instruction():
    env = make(n_exec_episodes=3)
    obs, info = env.reset(seed=5, options={"problem_id": HELD_OUT_PROBLEMS[0], "instruction": [5, 4]})
    assert info["problem_id"] == HELD_OUT_PROBLEMS[0]
    env.step(END_EPISODE)
    for _ in range(3):
        obs, _, terminated, _, _ = env.step(END_EPISODE)
        if not terminated:
            assert obs["instruction"].tolist() == [5, 4]
    assert terminated
    # A pin lasts one trial only.
    env.reset(seed=5)
    env.step(END_EPISODE)
    assert env.problem_id in env.problem_ids("train")


def test_seeding_reproducible():
    def rollout(seed):
        env = make(n_exec_episodes=2)
        rng = np.random.default_rng(0)
        out = []
        for trial in range(3):
            obs, info = env.reset(seed=seed if trial == 0 else None)
            out.append(info["problem_id"])
            terminated = False
            while not terminated:
                obs, reward, terminated, _, info = env.step(int(rng.integers(9)))
                out.append((obs["obs"].tolist(), obs["instruction"].tolist(), reward))
        return out

    assert rollout(7) == rollout(7)
    assert rollout(7) != rollout(8)


def test_bad_input():
    with pytest.raises(ValueError, match="split"):
        make(split="valid")
    with pytest.raises(ValueError, match="horizon"):
        make(horizon=0)
    env = make()
    for bad in (343, -1, 2.0):
        with pytest.raises(ValueError, match=r"options\['problem_id'\]"):
            env.reset(options={"problem_id": bad})
    # Ingredients absent from the problem (4, 7, 6).
    with pytest.raises(ValueError, match=r"options\['instruction'\].*\[4, 4\]"):
        env.reset(options={"problem_id": PROBLEM, "instruction": [1, 4]})
    for bad in ([0, 4], [4, 8], [4], [4, 6, 7]):
        with pytest.raises(ValueError, match=r"options\['instruction'\]"):
            env.reset(options={"problem_id": PROBLEM, "instruction": bad})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(9)


def test_gymnasium_and_sb3_env_checkers():
    from gymnasium.utils.env_checker import check_env as gym_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    gym_check_env(make(), skip_render_check=True)
    sb3_check_env(make(), warn=True)
    env = gym.make("MetaCook-v0", split="test")
    assert isinstance(env.unwrapped, MetaCookEnv) and env.unwrapped.split == "test"


def test_render():
    env = make(render_mode="rgb_array")
    env.reset(seed=0, options={"problem_id": PROBLEM, "instruction": [7, 6]})
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    shape = frame.shape
    before = frame.copy()
    run(env, [RIGHT, PICKUP])
    assert env.render().shape == shape and not np.array_equal(env.render(), before)
    # The problem is drawn: other fridge contents, another picture at the same state.
    env.reset(seed=0, options={"problem_id": problem_id_of((1, 2, 3))})
    assert not np.array_equal(env.render(), before)
    env = make()
    env.reset(seed=0)
    assert env.render() is None


# ---------------------------------------------------------------------------------------- oracle


def brute_force_value(contents, instruction, horizon: int = 20) -> float:
    """Optimal return of an execution episode by exhaustive search of the full-information MDP."""

    @functools.lru_cache(maxsize=None)
    def value(t, state):
        if t == horizon:
            return 0.0
        best = -0.1 * (horizon - t)  # the end-episode action
        for a in (LEFT, UP, RIGHT, DOWN, NOOP, RIDE_BUS, PICKUP, DROP):
            nxt, reward, done = cook_transition(state, a, contents, instruction)
            best = max(best, reward + (0.0 if done else value(t + 1, nxt)))
        return best

    return value(0, (1, 1, 0, 0, 0))


ORACLE_CASES = [
    ((4, 7, 6), (7, 7)),  # the middle fridge twice: 0.6
    ((4, 7, 6), (7, 6)),  # middle then corner: 0.4
    ((4, 7, 6), (4, 6)),  # two corners: 0.2
    ((4, 7, 6), (6, 4)),
    ((4, 7, 6), (4, 4)),
    ((5, 2, 5), (5, 2)),  # the same ingredient in both corners
    ((3, 3, 3), (3, 3)),  # one ingredient everywhere
    ((2, 2, 6), (6, 2)),  # A in a corner, B in the middle and a corner
    ((1, 5, 4), (5, 4)),  # a held-out problem and recipe
]


@pytest.mark.parametrize("contents,instruction", ORACLE_CASES)
def test_oracle_is_optimal_against_brute_force(contents, instruction):
    k = problem_id_of(contents)
    optimum = brute_force_value(contents, instruction)
    assert optimum == pytest.approx(optimal_execution_return(k, instruction))
    env = make(n_exec_episodes=2)
    result = play_trial(env, env.oracle(), seed=0, options={"problem_id": k, "instruction": list(instruction)})
    assert result["execution_returns"] == pytest.approx([optimum, optimum])
    assert result["exploration_length"] == 8  # three fridges opened in 7 steps, then end-episode
    # The trial records its exploration's actions (none of the execution's), which the env names.
    exploration = [RIGHT, PICKUP, DOWN, PICKUP, UP, UP, PICKUP, END_EPISODE]
    assert result["exploration_actions"] == exploration
    names = [env.unwrapped.action_names[a] for a in exploration]
    assert names == ["right", "pickup", "down", "pickup", "up", "up", "pickup", "end"]


def test_oracle_on_every_trial_and_split_means():
    env = make()
    oracle = env.oracle()
    returns = {}
    for k in range(343):
        for i in valid_instructions(k):
            result = play_trial(env, oracle, options={"problem_id": k, "instruction": list(i)})
            returns[k, i] = result["execution_returns"][0]
            assert returns[k, i] == pytest.approx(optimal_execution_return(k, i))
    assert set(np.round(list(returns.values()), 6)) == {0.2, 0.4, 0.6}
    # Split means (problem uniform, then recipe uniform), quoted in the report.
    expected_means = {"train": 0.3636, "test": 0.3431, "test_problems": 0.3278, "test_instructions": 0.3434}
    for split, expected in expected_means.items():
        means = [np.mean([returns[k, i] for i in env.instructions(k, split)]) for k in env.problem_ids(split)]
        assert np.mean(means) == pytest.approx(expected, abs=1e-4)


def test_oracle_uses_no_privileged_info_and_reads_final_obs():
    # Horizon 7: the third fridge is opened on the exploration's last step, seen only in final_obs.
    env = make(horizon=7)
    oracle = env.oracle()
    obs, info = env.reset(seed=0, options={"problem_id": PROBLEM})
    oracle.reset()
    info = public_info(info)
    assert "problem_id" not in info
    while True:
        obs, _, _, _, info = env.step(oracle.act(obs, public_info(info)))
        if info.get("episode_end"):
            break
    assert info["episode_length"] == 7 and info["final_obs"].tolist() == [2, 2, FRIDGE, 6, 0, 0]
    oracle.act(obs, public_info(info))
    assert oracle.known == {0: 4, 1: 7, 2: 6}
    assert dream_envs.make_oracle(gym.make("MetaCook-v0")).known == {}


def test_oracle_beats_random_agent():
    env = make(split="train")
    oracle, random_agent = env.oracle(), RandomAgent(env.action_space, seed=0)
    oracle_returns = [play_trial(env, oracle, seed=s)["execution_returns"][0] for s in range(100)]
    random_returns = [play_trial(env, random_agent, seed=s)["execution_returns"][0] for s in range(100)]
    assert min(oracle_returns) >= 0.2 - 1e-9
    assert np.mean(random_returns) < 0.0 < np.mean(oracle_returns)


class _Looper(ScriptedAgent):
    """Opens fridge 1 while exploring, then in execution steps right and loops pickup/drop there."""

    def act(self, obs, info):
        x = int(obs["obs"][0])
        if int(obs["phase"]) == EXPLORATION:
            if int(obs["prev_action"]) - 1 == PICKUP:
                return END_EPISODE
            return PICKUP if x == 2 else RIGHT
        if x != 2:
            return RIGHT
        return DROP if int(obs["prev_action"]) - 1 == PICKUP else PICKUP


def test_behaviour_report_counts_fridges_finished_recipes_and_undos():
    env = gym.make("MetaCook-v0", split="train", n_exec_episodes=2)
    oracle = behaviour_report(env, env.unwrapped.oracle(), n_trials=20)
    assert oracle.fridges_opened.tolist() == [3] * 20 and oracle.exploration_lengths.tolist() == [8] * 20
    assert len(oracle.execution_returns) == 40 and oracle.finished.all() and not oracle.ruined.any()
    assert np.allclose(oracle.execution_returns, oracle.optimal_returns) and not oracle.undos.any()
    assert "recipe finished in 100% of execution episodes (100% optimally)" in oracle.summary()
    assert oracle.stage_counts() == {-1: 0, 0: 0, 1: 0, 2: 0, 3: 0, 4: 40}
    assert oracle.second_pick_counts() == {"B": 40, "A": 0, "other": 0, "none": 0}
    assert (oracle.second_picks == oracle.instructions[:, 1]).all()

    # Problem (4, 7, 6): the looper picks 7 from fridge 1 ten times and lets it go nine times. When the
    # recipe starts with 7, each pick advances (+0.25) and each let-go undoes (-0.35): 9 undos and a
    # return of -0.1 + 2.5 - 3.15 = -0.75; otherwise every step costs -0.1 (-2.0), no undo.
    looper = behaviour_report(env, _Looper(), n_trials=20, problem_ids=[PROBLEM])
    assert looper.fridges_opened.tolist() == [1] * 20 and looper.exploration_lengths.tolist() == [3] * 20
    assert not looper.finished.any() and not looper.ruined.any()
    loops = looper.undos == 9
    assert looper.stages.tolist() == np.where(loops, 1, 0).tolist()  # ends holding 7 (a pick is last)
    assert set(looper.undos.tolist()) == {0, 9}
    assert np.allclose(looper.execution_returns, np.where(loops, -0.75, -2.0))
    assert looper.second_picks.tolist() == [-1] * 40  # never puts anything in the pot
    assert looper.second_pick_counts() == {"B": 0, "A": 0, "other": 0, "none": 0}
    with pytest.raises(ValueError, match="MetaCook-v0"):
        behaviour_report(gym.make("MetaBandit-v0"), _Looper(), n_trials=1)

    # Per recipe: none held out on the training split, unless asked for by name.
    assert looper.by_recipe() == {} and "held-out recipes" not in looper.summary()
    recipe = tuple(int(i) for i in looper.instructions[0])
    assert looper.by_recipe([recipe]) == {recipe: "0% (0%)"}


def test_cook_report_finished_optimally_only_at_the_optimal_return():
    # Three episodes of recipe (3, 6): finished in the fewest steps, finished two steps late, ruined.
    report = CookReport(
        fridges_opened=np.array([3]),
        exploration_lengths=np.array([8]),
        execution_returns=np.array([0.4, 0.2, -1.0]),
        optimal_returns=np.array([0.4, 0.4, 0.4]),
        stages=np.array([4, 4, RUINED]),
        undos=np.zeros(3, dtype=int),
        instructions=np.array([[3, 6]] * 3),
        second_picks=np.array([6, 6, 2]),
    )
    assert report.finished.tolist() == [True, True, False]
    assert report.finished_optimally.tolist() == [True, False, False]
    assert report.by_recipe([(3, 6)]) == {(3, 6): "67% (33%)"}
    assert "recipe finished in 67% of execution episodes (33% optimally)" in report.summary()


def test_behaviour_report_per_held_out_recipe():
    env = gym.make("MetaCook-v0", split="test_instructions")
    oracle = behaviour_report(env, env.unwrapped.oracle(), n_trials=30)
    assert set(map(tuple, oracle.instructions.tolist())) == set(HELD_OUT_INSTRUCTIONS)
    assert oracle.by_recipe() == {recipe: "100% (100%)" for recipe in HELD_OUT_INSTRUCTIONS}
    assert "held-out recipes finished (optimally): (3, 6) 100% (100%), (7, 1) 100% (100%)," in oracle.summary()


def test_replay_execution_tells_what_was_fetched_once_the_first_ingredient_was_in_the_pot():
    contents, recipe = (4, 7, 6), (7, 6)  # fridge 0 at (2, 0) holds 4, fridge 1 7, fridge 2 6
    put_a_in = [RIGHT, PICKUP, LEFT, DROP]  # 7 from fridge 1 into the pot: stage 2
    assert _replay_execution(contents, recipe, put_a_in + [RIGHT, UP, PICKUP, DOWN, LEFT, DROP]) == (4, 0, 6)
    assert _replay_execution(contents, recipe, put_a_in + [RIGHT, PICKUP]) == (2, 0, 7)  # A again
    assert _replay_execution(contents, recipe, put_a_in + [RIGHT, DOWN, PICKUP]) == (2, 0, 4)  # another
    assert _replay_execution(contents, recipe, put_a_in + [NOOP]) == (2, 0, 0)  # none
    assert _replay_execution(contents, recipe, [RIGHT, DOWN, PICKUP, UP, PICKUP]) == (1, 0, -1)  # A not in yet
    ruined = [RIGHT, DOWN, PICKUP, LEFT, UP, DROP, RIGHT, UP, PICKUP]  # 4 into the pot first
    assert _replay_execution(contents, recipe, ruined) == (-1, 1, -1)  # ruining the dish sets it back


def test_first_openings_and_their_rewards():
    # From the pot: right to fridge 1, pick twice, up to fridge 2, down twice to fridge 0, pick, back
    # up to fridge 1 and pick again: fridges 1, 2 and 0 first opened at steps 1, 4 and 7.
    actions = [RIGHT, PICKUP, PICKUP, UP, PICKUP, DOWN, DOWN, PICKUP, UP, PICKUP]
    state, states = (*START, 0, 0, 0), []
    for action in actions:
        states.append(state)
        state, _, _ = cook_transition(state, action, (4, 7, 6), None)
    states = np.array(states + [state])
    assert first_openings(states, np.array(actions)) == [(1, 1), (4, 2), (7, 0)]
    assert first_openings(states[:4], np.array(actions[:3])) == [(1, 1)]  # repeated picks count once
    assert first_openings(states[:1], np.array([], dtype=np.int64)) == []
    # the reward of each first opening, keyed by (fridge, order), over two trajectories
    rewards = np.arange(10.0)
    trajectories = [(states, np.array(actions)), (states[:4], np.array(actions[:3]))]
    found = opening_rewards(trajectories, [rewards, -rewards[:3]])
    assert list(found) == [(0, 2), (1, 0), (2, 1)]  # sorted by fridge
    assert found[1, 0].tolist() == [1.0, -1.0] and found[2, 1].tolist() == [4.0] and found[0, 2].tolist() == [7.0]
