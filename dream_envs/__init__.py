"""Meta-RL environments in the instruction-based meta-RL (IMRL) setting, as Gymnasium trial envs.

Importing this package registers ``MetaBus-v0``, ``MetaCook-v0``, ``SignNav3D-v0`` and
``MetaBandit-v0``. One Gymnasium episode is one trial: an exploration episode, then
``n_exec_episodes`` execution episodes (see :mod:`dream_envs.trial_env`).
"""

import functools
import importlib
from typing import Tuple

import gymnasium as gym
from gymnasium.envs.registration import register, registry

from dream_envs.agents import BatchTrialAgent, RandomAgent, ScriptedAgent, SingleTrialAgent
from dream_envs.pearl_ub import pearl_ub
from dream_envs.play import play_trial, play_trials, play_trials_batched
from dream_envs.trial_env import EXECUTION, EXPLORATION, SPLITS, TrialEnv, check_trial_spec, public_info

ENV_IDS = {
    "MetaBus-v0": "dream_envs.bus:MetaBusEnv",
    "MetaCook-v0": "dream_envs.cook:MetaCookEnv",
    "SignNav3D-v0": "dream_envs.sign_nav:SignNav3DEnv",
    "MetaBandit-v0": "dream_envs.bandit:MetaBanditEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry_point)


def env_splits(env_id: str) -> Tuple[str, ...]:
    """The splits of a registered trial env (its class's ``splits``), without making the env.

    ``env_id`` may name the module that registers it, as in ``gym.make("module:EnvId")``.
    """
    module, _, name = env_id.rpartition(":")
    if module:
        importlib.import_module(module)
    entry_point = gym.spec(name).entry_point
    if isinstance(entry_point, str):
        module, _, name = entry_point.partition(":")
        entry_point = getattr(importlib.import_module(module), name)
    return tuple(getattr(entry_point, "splits", SPLITS))


@functools.lru_cache(maxsize=None)  # ENV_IDS is fixed: validators call this once per value checked
def all_splits() -> Tuple[str, ...]:
    """Every split name that some env of this package offers ("train", "test", "all" first)."""
    return tuple(dict.fromkeys(split for env_id in ENV_IDS for split in env_splits(env_id)))


def make_oracle(env) -> ScriptedAgent:
    """The optimal scripted agent (optimal explorer + executor) of a trial env (or a wrapper of one)."""
    return env.unwrapped.oracle()


__all__ = [
    "ENV_IDS",
    "SPLITS",
    "EXECUTION",
    "EXPLORATION",
    "BatchTrialAgent",
    "RandomAgent",
    "ScriptedAgent",
    "SingleTrialAgent",
    "TrialEnv",
    "all_splits",
    "check_trial_spec",
    "env_splits",
    "make_oracle",
    "pearl_ub",
    "play_trial",
    "play_trials",
    "play_trials_batched",
    "public_info",
]
