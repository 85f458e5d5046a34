"""Saves are atomic, and hyperparameters are checked with errors that name them."""

from __future__ import annotations

import random
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from sb3_dream import DREAM, RL2DQN

SAVER = textwrap.dedent(
    """
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
    """
)


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
