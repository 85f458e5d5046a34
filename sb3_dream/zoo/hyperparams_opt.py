"""Optuna samplers for ``sb3-dream-zoo train --algo dream|rl2_dqn --optimize``.

Each sampler has rl-zoo3's signature ``(trial, n_actions, n_envs, additional_args) -> kwargs`` and
returns constructor arguments that override the hyperparameter file. Optuna parameters are named
after the constructor arguments, so the converters (rl-zoo3's ``HYPERPARAMS_CONVERTER``, used by
``--storage ... --study-name ... --trial-id``) only copy them.

The ranges centre on the paper's values (Appendix B.4) and reach the faster schedules of the
``fast`` preset (:mod:`sb3_dream.presets`): learning starts, epsilon decay and target syncs.
Networks, losses and the update ratio (one update per 4 env steps) are not searched.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Dict

if TYPE_CHECKING:  # optuna comes with rl-zoo3; only the trial object is used here
    import optuna


def sample_dream_params(trial: "optuna.Trial", n_actions: int, n_envs: int, additional_args: dict) -> Dict[str, Any]:
    """DREAM: learning rate, target syncs, epsilon decay, learning starts and the exploration reward."""
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "target_update_interval": trial.suggest_int("target_update_interval", 100, 10_000, log=True),
        "eps_decay_steps": trial.suggest_int("eps_decay_steps", 10_000, 500_000, log=True),
        "exploration_learning_starts": trial.suggest_int("exploration_learning_starts", 10, 8_000, log=True),
        "execution_learning_starts": trial.suggest_int("execution_learning_starts", 10, 1_000, log=True),
        "reward_penalty": trial.suggest_float("reward_penalty", 1e-3, 0.1, log=True),
        "encoder_variance": trial.suggest_float("encoder_variance", 0.01, 1.0, log=True),
        "bottleneck_threshold": trial.suggest_float("bottleneck_threshold", 1.0, 100.0, log=True),
    }


def sample_rl2_dqn_params(trial: "optuna.Trial", n_actions: int, n_envs: int, additional_args: dict) -> Dict[str, Any]:
    """RL2DQN: learning rate, target syncs, epsilon schedule, learning starts and the TD loss."""
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
        "target_update_interval": trial.suggest_int("target_update_interval", 100, 10_000, log=True),
        "exploration_steps": trial.suggest_int("exploration_steps", 20_000, 1_000_000, log=True),
        "exploration_final_eps": trial.suggest_float("exploration_final_eps", 0.0, 0.1),
        "learning_starts": trial.suggest_int("learning_starts", 100, 20_000, log=True),
        "td_loss": trial.suggest_categorical("td_loss", ["mse", "huber"]),
    }


def convert_params(params: Dict[str, Any]) -> Dict[str, Any]:
    """A stored trial's parameters as constructor arguments (they share names)."""
    return dict(params)


SAMPLERS: Dict[str, Callable[..., Dict[str, Any]]] = {"dream": sample_dream_params, "rl2_dqn": sample_rl2_dqn_params}
CONVERTERS: Dict[str, Callable[[Dict[str, Any]], Dict[str, Any]]] = {"dream": convert_params, "rl2_dqn": convert_params}
