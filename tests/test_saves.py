"""Nothing lost, nothing silently wrong: atomic saves, checked hyperparameters, checked trial shapes."""

from __future__ import annotations

import random
import subprocess
import sys
import textwrap
import time

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dream import DREAM, RL2DQN, evaluate_meta

SAVER = textwrap.dedent("""
    import sys
    import torch
    from sb3_dream import DREAM
    torch.set_num_threads(1)
    model = DREAM("MetaBus-v0", seed=0, execution_buffer_size=200_000, exploration_learning_starts=10**6)
    model.learn(400)
    model.save(sys.argv[1])
    model.save_replay_buffer(sys.argv[2])
    print("saved", flush=True)
    while True:
        model.save(sys.argv[1])
        model.save_replay_buffer(sys.argv[2])
    """)


def test_a_save_killed_mid_write_leaves_the_previous_file_intact(tmp_path):
    script, zip_path, pkl_path = tmp_path / "saver.py", tmp_path / "model.zip", tmp_path / "replay.pkl"
    script.write_text(SAVER)
    rng = random.Random(0)
    for _ in range(3):  # each run rewrites both files in a loop until it is killed at a random moment
        saver = subprocess.Popen([sys.executable, str(script), str(zip_path), str(pkl_path)], stdout=subprocess.PIPE)
        try:
            assert saver.stdout.readline() == b"saved\n"
            time.sleep(rng.uniform(0.2, 1.0))
        finally:
            saver.kill()
            saver.wait()
        model = DREAM.load(zip_path)
        model.load_replay_buffer(pkl_path)
        assert model.num_timesteps == 400 and len(model.replay_buffer.execution) > 0
    # what is left beside them: the killed writes' temporary files, never a half-written target
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "model.zip",
        "replay.pkl",
        "saver.py",
    ]


def test_saves_write_where_sb3_does(tmp_path):
    model = RL2DQN("MetaBandit-v0", buffer_size=10)
    model.save(tmp_path / "a")  # SB3 adds .zip to a path without a suffix
    model.save(tmp_path / "b.model")  # and keeps a suffix it is given
    model.save_replay_buffer(tmp_path / "c")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zip", "b.model", "c.pkl"]
    (tmp_path / "plain").write_bytes(b"")  # saved files get the permissions of any new file
    assert {p.stat().st_mode for p in tmp_path.iterdir()} == {(tmp_path / "plain").stat().st_mode}
    RL2DQN.load(tmp_path / "b.model")


@pytest.mark.parametrize("algo", [DREAM, RL2DQN])
@pytest.mark.parametrize(
    "name, value",
    [
        ("gamma", 1.5),
        ("gamma", -0.1),
        ("gamma", float("nan")),
        ("gamma", "0.9"),
        ("learning_rate", 0),
        ("learning_rate", -1e-4),
        ("stats_window_size", 0),
        ("batch_size", 0),
        ("max_grad_norm", -1.0),
        ("learning_starts", -1),
        ("gradient_steps", -1),
        ("train_freq", 0),
    ],
)
def test_bad_hyperparameters_name_themselves(algo, name, value):
    with pytest.raises(ValueError, match=name):
        algo("MetaBandit-v0", **{name: value})


def test_dream_checks_its_own_numbers():
    for name, value in [("reward_penalty", -1), ("encoder_variance", -0.1), ("bottleneck_threshold", np.inf)]:
        with pytest.raises(ValueError, match=name):
            DREAM("MetaBandit-v0", **{name: value})


# ---------------------------------------------------------------------- trial shapes
@pytest.fixture(scope="module")
def horizon_20_model():
    model = DREAM(gym.make("MetaBus-v0", variant="map"), seed=0, exploration_learning_starts=10**6)
    model.learn(100)
    return model


def test_a_model_meets_only_envs_of_its_trial_shape(horizon_20_model, tmp_path):
    model = horizon_20_model
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "replay")
    other_horizon = gym.make("MetaBus-v0", variant="map", horizon=30)
    with pytest.raises(ValueError, match="horizon is 30, the model's is 20"):
        model.set_env(other_horizon)
    with pytest.raises(ValueError, match="horizon is 30, the model's is 20"):
        DREAM.load(tmp_path / "model", env=other_horizon)
    with pytest.raises(ValueError, match="the evaluation env.*horizon is 30"):
        evaluate_meta(model, "MetaBus-v0", n_trials=2, env_kwargs={"variant": "map", "horizon": 30})
    with pytest.raises(ValueError, match="family is 'MetaCookEnv'"):
        evaluate_meta(model, "MetaCook-v0", n_trials=2)
    # rewards and an instruction in the exploration episode are inputs a model was trained with or without
    with pytest.raises(ValueError, match="reward_free_exploration is False, the model's is True"):
        model.set_env(gym.make("MetaBus-v0", variant="map", reward_free_exploration=False))
    # what may differ: the split, and the execution episodes per trial at meta-test
    evaluate_meta(model, "MetaBus-v0", n_trials=2, split="train", n_exec_episodes=2, env_kwargs={"variant": "map"})
    DREAM.load(tmp_path / "model", env=gym.make("MetaBus-v0", variant="map", split="test"))
    # a replay buffer filled in another trial shape
    other = DREAM(gym.make("MetaBus-v0"), seed=0, exploration_learning_starts=10**6)
    other.learn(50)
    other.save_replay_buffer(tmp_path / "distracting")
    with pytest.raises(ValueError, match=r"replay buffer in .*distracting.* n_problems is 576, the model's is 24"):
        model.load_replay_buffer(tmp_path / "distracting")
    assert model.replay_buffer.trial_spec == model.trial_spec  # the model's own buffer is kept
    model.load_replay_buffer(tmp_path / "replay")


@pytest.mark.parametrize("algo", [DREAM, RL2DQN])
def test_a_vec_env_of_mixed_trial_shapes_is_refused(algo):
    mixed = DummyVecEnv([lambda: gym.make("MetaBus-v0"), lambda: gym.make("MetaBus-v0", variant="vanilla")])
    with pytest.raises(ValueError, match="sub-env 1 of the VecEnv does not match sub-env 0.*n_problems"):
        algo(mixed)
    lengths = DummyVecEnv([lambda: gym.make("MetaBus-v0"), lambda: gym.make("MetaBus-v0", n_exec_episodes=2)])
    with pytest.raises(ValueError, match="n_exec_episodes is 2, sub-env 0 of the VecEnv's is 1"):
        algo(lengths)


def test_rl2dqn_replay_buffers_carry_their_trial_shape(tmp_path):
    model = RL2DQN(gym.make("MetaBus-v0", variant="map"), buffer_size=10)
    model.save_replay_buffer(tmp_path / "map")
    other = RL2DQN(gym.make("MetaBus-v0"), buffer_size=10)
    with pytest.raises(ValueError, match="replay buffer .* does not match the model"):
        other.load_replay_buffer(tmp_path / "map")
