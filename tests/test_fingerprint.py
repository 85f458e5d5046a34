"""Training numerics are pinned: a short seeded run gives the same parameters and greedy actions.

The digests were recorded before the code was reorganised by concept (losses, acting, the shared
trial off-policy base) and must not change when code moves: a change here means the arithmetic
of an update, the order of random draws or the acting path changed. Floating-point results
depend on the torch build and the CPU, so the comparison runs on the stack the digests were
recorded with (the README's pinned CPU torch on x86-64) and is skipped elsewhere. Within it, the
math kernels torch and MKL pick differ with the CPU's instruction set and vendor: a CPU listed in
``EXPECTED_BY_CPU`` is held to its own digests, recorded there from a commit whose arithmetic the
listed digests already pinned (the same code gives both sets); any other CPU to the first
recording's, whose CPU was not written down."""

from __future__ import annotations

import hashlib
import platform

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from stable_baselines3.common.env_util import make_vec_env

from sb3_dream import DREAM, RL2DQN
from test_dream import FAST

RECORDED_ON = ("2.13.0", "x86_64")


def cpu_kernels() -> str:
    """The CPU features that choose torch's and MKL's kernels: instruction set and vendor."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            vendor = next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("vendor_id")), "?")
    except OSError:
        vendor = "?"
    return f"{th.backends.cpu.get_cpu_capability()} {vendor}"


def expected_digest(name: str) -> str:
    """The digest recorded for run ``name`` on this CPU's kernels (the first recording's elsewhere)."""
    return EXPECTED_BY_CPU.get(cpu_kernels(), EXPECTED)[name]


on_recorded_stack = pytest.mark.skipif(
    (th.__version__.split("+")[0], platform.machine()) != RECORDED_ON,
    reason=f"digests recorded with torch {RECORDED_ON[0]} on {RECORDED_ON[1]}",
)


def digest(model, env_id: str, **env_kwargs) -> str:
    """sha256 of every parameter and of the greedy actions over 5 seeded trials."""
    h = hashlib.sha256()
    for p in model.policy.parameters():
        h.update(p.detach().cpu().numpy().tobytes())
    env = gym.make(env_id, **env_kwargs)
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        state, start, done = None, np.ones(1, bool), False
        while not done:
            action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
            start = np.zeros(1, bool)
            obs, _, terminated, truncated, _ = env.step(int(action))
            h.update(np.int64(action).tobytes())
            done = terminated or truncated
    return h.hexdigest()[:16]


DREAM_SHORT = {**FAST, "parallel_updates": False}


@on_recorded_stack
@pytest.mark.parametrize(
    "options, expected",
    [
        ({}, "DREAM_DEFAULT"),
        ({"execution_sampling": "episodes", "policy_kwargs": {"execution_recurrent": True}}, "DREAM_RECURRENT"),
        ({"n_envs": 3, "execution_target_z": "encoder"}, "DREAM_VEC"),
    ],
)
def test_dream_training_is_bit_identical_to_the_recorded_run(options, expected):
    th.set_num_threads(1)
    options = dict(options)
    n_envs = options.pop("n_envs", 1)
    env = make_vec_env("MetaBus-v0", n_envs=n_envs, seed=0, env_kwargs={"variant": "map"})
    model = DREAM(env, seed=0, **DREAM_SHORT, **options)
    model.learn(1200)
    assert digest(model, "MetaBus-v0", variant="map") == expected_digest(expected)


@on_recorded_stack
@pytest.mark.parametrize(
    "policy_kwargs, expected",
    [
        ({}, "RL2DQN"),
        # Adam's per-parameter loop, RL2DQN's default before fused Adam: the digest recorded then
        ({"optimizer_kwargs": {"fused": False}}, "RL2DQN_LOOP_ADAM"),
    ],
)
def test_rl2dqn_training_is_bit_identical_to_the_recorded_run(policy_kwargs, expected):
    th.set_num_threads(1)
    model = RL2DQN(
        make_vec_env("MetaBus-v0", n_envs=2, seed=0, env_kwargs={"variant": "map"}),
        seed=0,
        learning_starts=200,
        target_update_interval=100,
        buffer_size=200,
        exploration_steps=1000,
        policy_kwargs=policy_kwargs,
    )
    model.learn(1200)
    assert digest(model, "MetaBus-v0", variant="map") == expected_digest(expected)


#: the first recording's digests (serve every CPU not in EXPECTED_BY_CPU)
EXPECTED = {
    "DREAM_DEFAULT": "db97ef318d4a36a3",
    "DREAM_RECURRENT": "6a7ff308e09139af",
    "DREAM_VEC": "105265a109407bdc",
    "RL2DQN": "71499928b539d9c5",  # fused Adam
    "RL2DQN_LOOP_ADAM": "12d13add58ed9719",
}

#: the same runs on other CPUs (`cpu_kernels()`), recorded with the code at 9a5cb60
EXPECTED_BY_CPU = {
    "AVX2 AuthenticAMD": {
        "DREAM_DEFAULT": "028ff930a1d43172",
        "DREAM_RECURRENT": "fc5c177c56622f2c",
        "DREAM_VEC": "4d1dc672158ca7bc",
        "RL2DQN": "088d9fd03cf89f3c",
        "RL2DQN_LOOP_ADAM": "61aac61045c9af48",
    },
}
