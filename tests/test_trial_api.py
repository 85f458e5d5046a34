"""The trial contract of dream_envs.trial_env, checked on MetaBandit-v0 and on a tiny env defined here."""

from __future__ import annotations

from typing import Any, Dict

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

import dream_envs
from dream_envs import EXECUTION, EXPLORATION, RandomAgent, ScriptedAgent, TrialEnv, play_trial, public_info


class CueEnv(TrialEnv):
    """A minimal user-written trial env: the problem (0 or 1) shows as a cue while exploring at step 1.

    Execution: action == problem earns 1 and ends the episode; any other action earns -1 and ends it.
    Problems 0 and 1; train = {0}, test = {1}. Instruction [1] or [2] (both valid everywhere).
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(
            inner_observation_space=spaces.MultiDiscrete([3, 3]),
            instruction_nvec=[3],
            n_actions=3,
            end_episode_action=2,
            horizon=3,
            **kwargs,
        )

    n_problems = 2  # type: ignore[assignment]

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return {"train": np.array([0]), "test": np.array([1]), "all": np.array([0, 1])}[split]

    def _sample_instruction(self, problem_id: int, split: str) -> np.ndarray:
        return np.array([1 + self.np_random.integers(2)])

    def _set_problem(self, problem_id: int) -> None:
        self.cue = problem_id

    def _inner_reset(self) -> np.ndarray:
        self.t = 0
        return np.array([0, 0])

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        self.t += 1
        shown = 1 + self.cue if self.phase == EXPLORATION and self.t == 1 else 0
        if self.instruction is None:
            return np.array([min(self.t, 2), shown]), 0.0, False
        return np.array([min(self.t, 2), shown]), (1.0 if action == self.cue else -1.0), True

    def _end_episode_reward(self, steps_remaining: int) -> float:
        return -0.5 * steps_remaining

    def _render_frame(self) -> np.ndarray:
        return np.zeros((4, 4, 3), np.uint8)


def rollout(env: gym.Env, actions, seed=0, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out = [(obs, None, False, info)]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append((obs, r, term, info))
        if term:
            break
    return out


def test_dict_observation_keys_and_spaces():
    env = CueEnv()
    assert set(env.observation_space.spaces) == {
        "obs",
        "instruction",
        "phase",
        "episode_start",
        "prev_action",
        "prev_reward",
    }
    assert env.observation_space["prev_action"].n == env.n_actions + 1
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs["phase"] == EXPLORATION and obs["episode_start"] == 1 and obs["prev_action"] == 0
    assert np.all(obs["instruction"] == 0) and obs["prev_reward"][0] == 0.0
    assert info == {"problem_id": 0, "phase": EXPLORATION, "episode_index": 0}


def test_trial_structure_rewards_and_info():
    env = CueEnv(n_exec_episodes=2, split="all")
    steps = rollout(env, [0, 1, 0, 1, 0], options={"problem_id": 1})
    # exploration: 3 steps (horizon), reward-free, the cue at step 1
    (o1, r1, t1, i1), (o2, r2, t2, i2), (o3, r3, t3, i3) = steps[1:4]
    assert o1["obs"].tolist() == [1, 2] and r1 == r2 == r3 == 0.0
    assert o1["episode_start"] == 0 and o1["prev_action"] == 1
    assert "episode_end" not in i2
    # the third step ends exploration: info describes it, obs is execution's first
    assert i3["episode_end"] and i3["episode_phase"] == EXPLORATION and i3["episode_length"] == 3
    assert i3["final_obs"].tolist() == [2, 0] and i3["episode_return"] == 0.0 and i3["episode_truncated"]
    assert o3["phase"] == EXECUTION and o3["episode_start"] == 1 and o3["instruction"][0] in (1, 2)
    assert o3["prev_action"] == 1  # carried across the boundary
    assert i3["episode_index"] == 1 and i3["phase"] == EXECUTION
    # execution 1: right action (1) gives +1 and ends; execution 2: wrong action gives -1, trial ends
    (o4, r4, t4, i4), (o5, r5, t5, i5) = steps[4:6]
    assert (r4, t4, i4["episode_return"], i4["episode_index"]) == (1.0, False, 1.0, 2)
    assert not i4["episode_truncated"]  # ended by the MDP
    assert o4["prev_reward"][0] == 1.0 and o4["episode_start"] == 1
    assert (r5, t5) == (-1.0, True) and i5["execution_returns"] == [1.0, -1.0]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_end_episode_action_and_its_reward():
    env = CueEnv(split="all")
    steps = rollout(env, [2, 2], options={"problem_id": 0})
    _, r, _, info = steps[1]
    assert r == 0.0 and info["episode_end"] and info["episode_length"] == 1  # exploration ends early, reward-free
    _, r, term, info = steps[2]
    assert r == -1.5 and term  # 3 steps remaining x -0.5


def test_exploration_with_rewards_variant():
    env = CueEnv(reward_free_exploration=False, split="all")
    obs, _ = env.reset(seed=0, options={"problem_id": 0})
    assert obs["instruction"][0] in (1, 2)
    obs, r, term, trunc, info = env.step(0)
    assert r == 1.0 and info["episode_end"] and info["episode_phase"] == EXPLORATION and not term


def test_problem_features_default_to_the_id():
    env = CueEnv()
    assert env.problem_nvec.tolist() == [2] and env.problem_feature_table().tolist() == [[0], [1]]


def test_splits_and_sampling():
    env = CueEnv(split="test")
    assert env.problem_ids().tolist() == [1] and env.problem_ids("all").tolist() == [0, 1]
    assert {env.reset(seed=s)[1]["problem_id"] for s in range(10)} == {1}


def test_pinning_problem_and_instruction():
    env = CueEnv(n_exec_episodes=4)
    env.reset(seed=0, options={"problem_id": 1, "instruction": [2]})  # pinning may leave the split
    obs, _, _, _, info = env.step(2)  # end exploration
    instructions = [int(obs["instruction"][0])]
    for _ in range(4):
        obs, _, term, _, info = env.step(0)
        instructions.append(int(obs["instruction"][0]))
    assert info["problem_id"] == 1 and term
    assert instructions == [2] * 5
    # without pinning, both instructions are sampled
    env.reset(seed=0, options={"problem_id": 1})
    seen = {int(env.step(2)[0]["instruction"][0])}
    for _ in range(3):
        seen.add(int(env.step(0)[0]["instruction"][0]))
    assert seen == {1, 2}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"split": "valid"}, "split='valid'.*'train', 'test', 'all'"),
        ({"n_exec_episodes": 0}, "n_exec_episodes"),
        ({"render_mode": "human"}, "render_mode='human'"),
        ({"reward_free_exploration": "yes"}, "reward_free_exploration"),
    ],
)
def test_bad_constructor_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CueEnv(**kwargs)


@pytest.mark.parametrize(
    "options, match",
    [
        ({"problem_id": 2}, r"problem_id.*0 \.\. 1"),
        ({"problem_id": -1}, "problem_id"),
        ({"problem_id": "0"}, "problem_id"),
        ({"instruction": [3]}, "instruction"),
        ({"instruction": [0]}, "instruction"),
        ({"instruction": [1, 1]}, "instruction"),
        ({"seed": 3}, "unknown keys"),
    ],
)
def test_bad_reset_options(options, match):
    with pytest.raises(ValueError, match=match):
        CueEnv().reset(options=options)


@pytest.mark.parametrize(
    "action", [5, -1, 1.5, True, "1", np.float32(1), np.bool_(True), np.array([1.0]), np.array([0, 1]), None]
)
def test_bad_action_is_refused_with_a_clear_error(action):
    env = CueEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action=.* accepted values: integers 0 \.\. 2"):
        env.step(action)


@pytest.mark.parametrize("action", [1, np.int64(1), np.int32(1), np.array([1]), np.array(1)])
def test_integer_actions_are_accepted(action):
    env = CueEnv()
    env.reset(seed=0)
    obs, *_ = env.step(action)
    assert obs["prev_action"] == 2  # action 1, shifted by one


def test_seeding_reproducible():
    def trace(seed):
        env = CueEnv(split="all", n_exec_episodes=3)
        agent = RandomAgent(env.action_space, seed=1)
        obs, info = env.reset(seed=seed)
        seq = [info["problem_id"]]
        done = False
        while not done:
            obs, r, done, _, info = env.step(agent.act(obs, info))
            seq += [obs["instruction"].tolist(), r]
        return seq

    assert trace(7) == trace(7)
    assert len({str(trace(s)) for s in range(10)}) > 1


def test_play_trial_hides_the_problem_id():
    seen = []

    class Spy(ScriptedAgent):
        def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
            seen.append(info)
            return 2

    result = play_trial(CueEnv(), Spy(), seed=0)
    assert result["problem_id"] == 0 and result["exploration_length"] == 1
    assert result["execution_returns"] == [-1.5] and result["trial_return"] == -1.5
    assert seen and all("problem_id" not in i for i in seen)
    assert public_info({"problem_id": 3, "phase": 1}) == {"phase": 1}


# ----------------------------------------------------------------------------- MetaBandit-v0


def test_bandit_rules():
    env = gym.make("MetaBandit-v0", n_actions=3, horizon=2, split="all").unwrapped
    assert env.n_problems == 9 and env.solution(5) == [2, 1]
    env.reset(seed=0, options={"problem_id": 5})
    env.step(0)
    _, r, _, _, info = env.step(0)  # a_* reveals the problem on the last state
    assert r == 0.0 and info["final_obs"].tolist() == [2, 1, 1, 6]
    obs, r, _, _, _ = env.step(2)
    assert obs["obs"].tolist() == [1, 3, 0, 0] and r == 0.0
    _, r, term, _, info = env.step(1)
    assert r == 1.0 and term and info["execution_returns"] == [1.0]
    # a non-a_* exploration reveals nothing, and a wrong execution sequence earns 0
    env.reset(seed=0, options={"problem_id": 5})
    env.step(1)
    _, _, _, _, info = env.step(0)
    assert info["final_obs"][-1] == 0
    env.step(2)
    assert env.step(2)[1] == 0.0


def test_bandit_observation_has_no_problem_id():
    env = gym.make("MetaBandit-v0", n_actions=4, horizon=1)
    first = [env.reset(options={"problem_id": k})[0] for k in range(4)]
    for obs in first[1:]:
        for key in obs:
            np.testing.assert_array_equal(obs[key], first[0][key])


@pytest.mark.parametrize("kwargs", [{}, {"n_actions": 2}, {"n_actions": 3, "horizon": 3, "n_exec_episodes": 2}])
def test_bandit_oracle_is_optimal_and_random_is_not(kwargs):
    env = gym.make("MetaBandit-v0", **kwargs)
    oracle, n_exec = dream_envs.make_oracle(env), kwargs.get("n_exec_episodes", 1)
    for k in env.unwrapped.problem_ids():
        assert play_trial(env, oracle, options={"problem_id": int(k)})["execution_returns"] == [1.0] * n_exec
    random = RandomAgent(env.action_space, seed=0)
    mean = np.mean([sum(play_trial(env, random, seed=s)["execution_returns"]) for s in range(300)])
    chance = n_exec / env.unwrapped.n_problems
    assert abs(mean - chance) < 0.1


def test_bandit_bad_arguments():
    with pytest.raises(ValueError, match="n_actions"):
        gym.make("MetaBandit-v0", n_actions=1)
    with pytest.raises(ValueError, match="horizon"):
        gym.make("MetaBandit-v0", horizon=0)


def test_final_frame_pictures_the_last_state_of_each_episode():
    env = gym.make("MetaBus-v0", render_mode="rgb_array", final_frames=True, n_exec_episodes=2)
    oracle = dream_envs.make_oracle(env)
    obs, info = env.reset(seed=0)
    previous, ends, terminated = env.render(), 0, False
    while not terminated:
        obs, _, terminated, _, info = env.step(oracle.act(obs, public_info(info)))
        if info.get("episode_end"):
            ends += 1
            assert not np.array_equal(info["final_frame"], previous)  # the state the last action reached
        else:
            assert "final_frame" not in info
        previous = env.render()
    assert ends == 3 and np.array_equal(info["final_frame"], previous)  # the trial's end: nothing new started


@pytest.mark.parametrize("env_id", ["MetaBus-v0", "MetaCook-v0", "MetaBandit-v0"])
def test_final_frames_are_drawn_only_when_asked_for(env_id):
    # SB3 builds every env from an ID with render_mode="rgb_array" (make_vec_env, DREAM("MetaBus-v0")):
    # training envs must not draw a picture per inner episode unless final_frames=True.
    rendered = {"render_mode": "rgb_array"}
    cases = [({}, False), (rendered, False), ({**rendered, "final_frames": True}, True)]
    for kwargs, drawn in cases:
        env = gym.make(env_id, **kwargs)
        env.reset(seed=0)
        info = {}
        while not info.get("episode_end"):
            *_, info = env.step(env.action_space.sample())
        assert ("final_frame" in info) == drawn, kwargs
    vec = make_vec_env(env_id, n_envs=2, seed=0)
    assert vec.get_attr("render_mode") == ["rgb_array"] * 2 and vec.get_attr("final_frames") == [False, False]


def test_final_frames_bad_arguments():
    with pytest.raises(ValueError, match="final_frames=True needs render_mode='rgb_array', got render_mode=None"):
        gym.make("MetaBus-v0", final_frames=True)
    with pytest.raises(ValueError, match="final_frames must be True or False, got 1"):
        gym.make("MetaBus-v0", render_mode="rgb_array", final_frames=1)
