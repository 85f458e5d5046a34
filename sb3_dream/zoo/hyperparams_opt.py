"""Optuna samplers for ``sb3-dream-zoo train --algo dream|rl2_dqn|import_dqn|varibad --optimize``.

Each sampler has rl-zoo3's signature ``(trial, n_actions, n_envs, additional_args) -> kwargs`` and
returns constructor arguments that override the hyperparameter file. Optuna parameters are named
after the constructor arguments (DREAM's ``execution_body`` names its ``policy_kwargs``), which
the converters (rl-zoo3's ``HYPERPARAMS_CONVERTER``, used by ``--storage ... --study-name ...
--trial-id`` and by ``sb3-dream-zoo train --best-trial``) turn them back into.

The ranges centre on the paper's values (Appendix B.4) and reach the faster schedules of the
``fast`` preset (:mod:`sb3_dream.presets`): learning starts, epsilon decay and target syncs.
DREAM's execution body is searched among three widths; the other networks, the losses and the
update ratio (one update per 4 env steps) are not.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Dict, Tuple

if TYPE_CHECKING:  # optuna comes with rl-zoo3; only the trial object is used here
    import optuna


# DREAM's execution body (DreamPolicy's ``execution_hidden_sizes``), by the name a trial stores.
EXECUTION_BODIES: Dict[str, Tuple[int, ...]] = {"64": (64,), "128x128": (128, 128), "256x256": (256, 256)}


def sample_dream_params(trial: "optuna.Trial", n_actions: int, n_envs: int, additional_args: dict) -> Dict[str, Any]:
    """DREAM: the execution body, c (``reward_penalty``), the learning rate, the epsilon schedule,
    ``execution_sampling``, target syncs and when exploration learning starts.

    The body replaces the hyperparameter file's ``policy_kwargs`` during the search."""
    return convert_dream_params(
        {
            "learning_rate": trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True),
            "reward_penalty": trial.suggest_float("reward_penalty", 1e-3, 0.3, log=True),
            "eps_decay_steps": trial.suggest_int("eps_decay_steps", 10_000, 500_000, log=True),
            "exploration_final_eps": trial.suggest_float("exploration_final_eps", 0.0, 0.1),
            "execution_sampling": trial.suggest_categorical("execution_sampling", ["transitions", "episodes"]),
            "execution_body": trial.suggest_categorical("execution_body", list(EXECUTION_BODIES)),
            "target_update_interval": trial.suggest_int("target_update_interval", 100, 10_000, log=True),
            "exploration_learning_starts": trial.suggest_int("exploration_learning_starts", 10, 8_000, log=True),
        }
    )


def convert_dream_params(params: Dict[str, Any]) -> Dict[str, Any]:
    """A stored DREAM trial's parameters as constructor arguments (``execution_body`` becomes
    ``policy_kwargs``; the others share their names)."""
    kwargs = dict(params)
    body = kwargs.pop("execution_body", None)
    if body is not None:
        kwargs["policy_kwargs"] = {"execution_hidden_sizes": EXECUTION_BODIES[body]}
    return kwargs


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


def sample_import_dqn_params(
    trial: "optuna.Trial", n_actions: int, n_envs: int, additional_args: dict
) -> Dict[str, Any]:
    """IMPORT: RL2DQN's search and the auxiliary loss's weight (the authors': 1)."""
    return {
        **sample_rl2_dqn_params(trial, n_actions, n_envs, additional_args),
        "aux_loss_coef": trial.suggest_float("aux_loss_coef", 0.01, 1.0, log=True),
    }


def sample_varibad_params(trial: "optuna.Trial", n_actions: int, n_envs: int, additional_args: dict) -> Dict[str, Any]:
    """VariBAD: RL2DQN's search and the decoders' loss weight (1)."""
    return {
        **sample_rl2_dqn_params(trial, n_actions, n_envs, additional_args),
        "decoder_loss_coef": trial.suggest_float("decoder_loss_coef", 0.01, 1.0, log=True),
    }


def convert_params(params: Dict[str, Any]) -> Dict[str, Any]:
    """A stored trial's parameters as constructor arguments (they share names)."""
    return dict(params)


SAMPLERS: Dict[str, Callable[..., Dict[str, Any]]] = {
    "dream": sample_dream_params,
    "rl2_dqn": sample_rl2_dqn_params,
    "import_dqn": sample_import_dqn_params,
    "varibad": sample_varibad_params,
}
CONVERTERS: Dict[str, Callable[[Dict[str, Any]], Dict[str, Any]]] = {
    "dream": convert_dream_params,
    "rl2_dqn": convert_params,
    "import_dqn": convert_params,
    "varibad": convert_params,
}


def meta_test_trial_eval_callback() -> type:
    """rl-zoo3's ``TrialEvalCallback`` with the held-out meta-test return as what each trial reports
    (and is pruned on) when the evaluation env is a trial env: :func:`sb3_dream.evaluation.evaluate_meta`
    of ``--eval-episodes`` trials on the split of the evaluation env (``test`` unless
    ``--eval-env-kwargs`` say otherwise), the same trials at every evaluation. Other envs keep
    rl-zoo3's episode return."""
    from rl_zoo3.callbacks import TrialEvalCallback

    class MetaTestTrialEvalCallback(TrialEvalCallback):
        def _on_step(self) -> bool:
            spec = _trial_env_spec(self.eval_env)
            if spec is None or not (self.eval_freq > 0 and self.n_calls % self.eval_freq == 0):
                return super()._on_step()
            from sb3_dream.evaluation import evaluate_meta

            env_id, kwargs = spec
            result = evaluate_meta(
                self.model,
                env_id,
                n_trials=self.n_eval_episodes,
                split=kwargs.pop("split", "test"),
                n_exec_episodes=int(kwargs.pop("n_exec_episodes", 1)),
                deterministic=self.deterministic,
                env_kwargs=kwargs,
            )
            self.last_mean_reward = float(result.mean)
            self.eval_idx += 1
            if self.verbose > 0:
                print(f"Eval num_timesteps={self.num_timesteps}, meta-test return={result.mean:.3f}")
            self.trial.report(self.last_mean_reward, self.eval_idx)
            if self.trial.should_prune():
                self.is_pruned = True
                return False
            return True

    return MetaTestTrialEvalCallback


def _trial_env_spec(vec_env: Any) -> Any:
    """(env ID, constructor arguments) of the trial env behind ``vec_env``, or None for another env."""
    from dream_envs import TrialEnv

    try:
        env = vec_env.unwrapped.envs[0] if hasattr(vec_env, "unwrapped") else vec_env.envs[0]
    except (AttributeError, IndexError):
        return None
    inner = getattr(env, "unwrapped", env)
    if not isinstance(inner, TrialEnv) or inner.spec is None:
        return None
    return inner.spec.id, dict(inner.spec.kwargs or {})
