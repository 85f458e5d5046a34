"""Meta-RL environments in the instruction-based meta-RL (IMRL) setting, as Gymnasium trial envs.

Importing this package registers ``MetaBus-v0``, ``MetaCook-v0``, ``SignNav3D-v0`` and
``MetaBandit-v0``. One Gymnasium episode is one trial: an exploration episode, then
``n_exec_episodes`` execution episodes (see :mod:`dream_envs.core`).
"""

from gymnasium.envs.registration import register, registry

from dream_envs.core import (
    EXECUTION,
    EXPLORATION,
    RandomAgent,
    ScriptedAgent,
    TrialEnv,
    play_trial,
    play_trials,
    public_info,
)

ENV_IDS = {
    "MetaBus-v0": "dream_envs.bus:MetaBusEnv",
    "MetaCook-v0": "dream_envs.cook:MetaCookEnv",
    "SignNav3D-v0": "dream_envs.sign_nav:SignNav3DEnv",
    "MetaBandit-v0": "dream_envs.bandit:MetaBanditEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry_point)


def make_oracle(env) -> ScriptedAgent:
    """The optimal scripted agent (optimal explorer + executor) of a trial env (or a wrapper of one)."""
    return env.unwrapped.oracle()


__all__ = [
    "ENV_IDS",
    "EXECUTION",
    "EXPLORATION",
    "RandomAgent",
    "ScriptedAgent",
    "TrialEnv",
    "make_oracle",
    "play_trial",
    "play_trials",
    "public_info",
]
