"""What every registered trial env must do: checkers, vectorised use, the oracle beating random."""

from __future__ import annotations

import importlib

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import dream_envs
from dream_envs import RandomAgent, play_trial

ENV_IDS = list(dream_envs.ENV_IDS)


def _available(env_id: str) -> bool:
    try:
        importlib.import_module(dream_envs.ENV_IDS[env_id].split(":")[0])
        return True
    except ModuleNotFoundError:
        return False


@pytest.fixture(params=[pytest.param(e, marks=pytest.mark.opengl) if e == "SignNav3D-v0" else e for e in ENV_IDS])
def env_id(request):
    if not _available(request.param):
        pytest.fail(f"{request.param} is registered but its module is missing")
    return request.param


def test_checkers(env_id):
    env = gym.make(env_id)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(env.unwrapped, warn=True)
    env.close()


def test_render_rgb_array(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3 and min(frame.shape[:2]) >= 60
    assert frame.std() > 0  # not a blank image
    env.close()


def test_problem_id_only_in_info(env_id):
    env = gym.make(env_id, split="all")
    obs, info = env.reset(seed=0)
    assert "problem_id" in info and "problem_id" not in obs
    assert 0 <= info["problem_id"] < env.unwrapped.n_problems
    assert set(env.unwrapped.problem_ids("train")) | set(env.unwrapped.problem_ids("test")) <= set(
        env.unwrapped.problem_ids("all")
    )
    env.close()


def test_oracle_beats_random(env_id):
    env = gym.make(env_id)
    oracle, random = dream_envs.make_oracle(env), RandomAgent(env.action_space, seed=0)
    n = 3 if env_id == "SignNav3D-v0" else 20
    best = np.mean([play_trial(env, oracle, seed=s)["execution_returns"][0] for s in range(n)])
    chance = np.mean([play_trial(env, random, seed=s)["execution_returns"][0] for s in range(n)])
    assert best > chance
    env.close()


class OraclePerEnv(dream_envs.BatchTrialAgent):
    """A batch agent that runs one oracle per env (checks the side-by-side runner on its own)."""

    def __init__(self, env_id):
        self.env_id, self.oracles = env_id, []

    def reset(self, n_envs):
        self.oracles = [dream_envs.make_oracle(gym.make(self.env_id)) for _ in range(n_envs)]
        self.idle_infos = 0

    def start_trials(self, idx):
        for i in idx:
            self.oracles[i].reset()

    def act(self, obs, infos):
        actions = np.zeros(len(infos), dtype=np.int64)
        for i, info in enumerate(infos):
            if not info:  # an env with no trial left
                self.idle_infos += 1
                continue
            actions[i] = self.oracles[i].act({k: v[i] for k, v in obs.items()}, info)
        return actions


@pytest.mark.parametrize("env_id", ["MetaBus-v0", "MetaCook-v0", "MetaBandit-v0"])
def test_trials_side_by_side_are_the_trials_played_one_at_a_time(env_id):
    env = gym.make(env_id, split="test")
    one = list(dream_envs.play_trials(env, dream_envs.make_oracle(env), 7, seed=4, problem_ids=[3, 5]))
    agent = OraclePerEnv(env_id)
    side = dream_envs.play_trials_batched([gym.make(env_id, split="test") for _ in range(3)], agent, 7, 4, [3, 5])
    assert side == one and [r["problem_id"] for r in side] == [3, 5] * 3 + [3]
    assert agent.idle_infos > 0  # the last trial ran with the other envs idle
    assert len(dream_envs.play_trials_batched([env] * 2, OraclePerEnv(env_id), 1)) == 1  # more envs than trials
    with pytest.raises(ValueError, match="envs must not be empty"):
        dream_envs.play_trials_batched([], agent, 2)
    with pytest.raises(ValueError, match="n_trials"):
        dream_envs.play_trials_batched([env], agent, 0)


@pytest.mark.parametrize("vec_env_cls", [DummyVecEnv, SubprocVecEnv])
def test_vectorised_auto_reset_draws_new_problems(env_id, vec_env_cls):
    n_envs = 2 if env_id == "SignNav3D-v0" else 8
    # Subprocesses start fresh: "module:EnvID" makes Gymnasium import dream_envs there first.
    vec = make_vec_env(f"dream_envs:{env_id}", n_envs=n_envs, seed=0, vec_env_cls=vec_env_cls)
    obs = vec.reset()
    assert obs["obs"].shape[0] == n_envs
    rng = np.random.default_rng(0)
    problems, trials_done = set(), 0
    for _ in range(60):
        obs, rewards, dones, infos = vec.step(rng.integers(vec.action_space.n, size=n_envs))
        assert rewards.shape == (n_envs,)
        for done, info in zip(dones, infos):
            problems.add(info["problem_id"])
            if done:
                trials_done += 1
                assert "terminal_observation" in info and "execution_returns" in info
    vec.close()
    assert trials_done > 0
    if len(gym.make(env_id).unwrapped.problem_ids()) > 1:
        assert len(problems) > 1


def test_problem_features_are_a_structured_injective_representation(env_id):
    env = gym.make(env_id).unwrapped
    table = env.problem_feature_table()
    nvec = env.problem_nvec
    assert table.shape == (env.n_problems, len(nvec))
    assert (table >= 0).all() and (table < nvec).all()
    assert len({tuple(row) for row in table}) == env.n_problems  # distinct problems stay distinct


def test_paper_problem_representations():
    bus = gym.make("MetaBus-v0").unwrapped
    assert bus.problem_nvec.tolist() == [24, 4, 4, 4, 4]
    assert bus.problem_features(24 * 23 + 5).tolist() == [5, 3, 2, 1, 0]
    assert gym.make("MetaBus-v0", variant="map").unwrapped.problem_nvec.tolist() == [24]
    cook = gym.make("MetaCook-v0").unwrapped
    assert cook.problem_nvec.tolist() == [7, 7, 7] and cook.problem_features(1 + 7 * 2).tolist() == [1, 2, 0]


def test_env_splits_are_read_from_the_class_without_making_the_env():
    common = ("train", "test", "all")
    assert dream_envs.env_splits("MetaBus-v0") == common
    # The module:ID form, as in gym.make, and the family's own splits after the common ones.
    assert dream_envs.env_splits("dream_envs:MetaCook-v0") == (*common, "test_problems", "test_instructions")
    for env_id in dream_envs.ENV_IDS:
        assert dream_envs.env_splits(env_id)[:3] == common
    assert dream_envs.all_splits() == (*common, "test_problems", "test_instructions")
    with pytest.raises(gym.error.Error):
        dream_envs.env_splits("NoSuchEnv-v0")


def test_check_choice_names_the_argument_and_keeps_booleans_apart():
    from dream_envs.checks import check_choice

    assert check_choice("mode", "auto", (True, False, "auto")) == "auto"
    assert check_choice("mode", False, (True, False, "auto")) is False
    assert check_choice("size", 2, (1, 2, 3)) == 2
    # 1 == True and 0 == False in Python; neither is accepted in place of the other.
    for name, value, choices in (("mode", 1, (True, False)), ("mode", 0, (True, False)), ("size", True, (1, 2))):
        with pytest.raises(ValueError, match=f"{name}={value!r} is not valid; accepted values: "):
            check_choice(name, value, choices)
    with pytest.raises(ValueError, match="split='val' is not valid; accepted values: 'train', 'test'"):
        check_choice("split", "val", ("train", "test"))


def test_trial_cases_are_the_distribution_trials_are_drawn_from(env_id):
    """Every (problem, instruction) pair of trial_cases, with the frequency its probability says:
    resets draw the problem and ``_sample_instruction`` (what each execution episode calls) the
    instruction; each pair's count lies within 4.5 standard deviations of its expected count."""
    env = gym.make(env_id, split="test")
    trial_env = env.unwrapped
    pids, instructions, probabilities = trial_env.trial_cases()
    assert len(pids) == len(instructions) == len(probabilities) and np.isclose(probabilities.sum(), 1.0)
    assert set(pids.tolist()) == set(trial_env.problem_ids().tolist())
    index = {(int(k), tuple(i)): c for c, (k, i) in enumerate(zip(pids, instructions.tolist()))}
    assert len(index) == len(pids)  # no pair twice
    n_draws = 600 if env_id == "SignNav3D-v0" else 20_000  # its reset lays out a 3D room
    counts = np.zeros(len(pids))
    for draw in range(n_draws):
        _, info = env.reset(seed=draw)
        instruction = trial_env._sample_instruction(info["problem_id"], trial_env.split)
        counts[index[(info["problem_id"], tuple(int(x) for x in instruction))]] += 1
    spread = np.sqrt(n_draws * probabilities * (1 - probabilities))
    assert np.all(np.abs(counts - n_draws * probabilities) <= 4.5 * spread + 1)
    env.close()
