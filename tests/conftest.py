"""Test-wide settings and shared fixtures."""

import gymnasium as gym
import numpy as np
import pytest
import torch

# The networks are small: one intra-op thread is fastest on a 2-core machine and keeps CPU time
# predictable when other processes share it.
torch.set_num_threads(1)


class _RecordActions(gym.Wrapper):
    """Records every action of each trial under the seed its ``reset`` was given."""

    def __init__(self, env: gym.Env, log: dict) -> None:
        super().__init__(env)
        self.log = log

    def reset(self, *, seed=None, options=None):
        self.actions = self.log.setdefault(seed, [])
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        self.actions.append(int(action))
        return self.env.step(action)


@pytest.fixture
def played_side_by_side():
    """``check(model, env_id, n_trials, n_envs, split)``: plays ``n_trials`` trials of ``model``
    one at a time and then side by side in ``n_envs`` envs (``sb3_dream.evaluation.evaluate_meta``),
    asserts that every trial got the same actions and results both ways, and returns the actions
    of each trial (by its seed)."""

    def check(model, env_id: str, n_trials: int = 11, n_envs: int = 4, split: str = "test") -> dict:
        from sb3_dream.evaluation import evaluate_meta

        logs, results = [], []
        for n in (1, n_envs):
            log: dict = {}
            envs = [_RecordActions(gym.make(env_id, split=split), log) for _ in range(n)]
            results.append(evaluate_meta(model, envs, n_trials, split=split, seed=3, n_envs=n))
            logs.append(log)
        assert logs[0] == logs[1] and len(logs[0]) == n_trials
        for key in ("returns", "exploration_lengths", "problem_ids"):
            np.testing.assert_array_equal(getattr(results[0], key), getattr(results[1], key))
        return logs[0]

    return check


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "opengl: builds SignNav3D-v0, which needs OpenGL (skipped, with the reason, without it)"
    )


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked ``opengl`` where SignNav3D-v0 cannot be built, saying why."""
    needs_opengl = [item for item in items if item.get_closest_marker("opengl")]
    if not needs_opengl:
        return
    from dream_envs.sign_nav import opengl_available

    available, reason = opengl_available()
    if not available:
        for item in needs_opengl:
            item.add_marker(pytest.mark.skip(reason=reason))
