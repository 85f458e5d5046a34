"""The learn loop shared by the trial algorithms (RL2DQN, DREAM)."""

from __future__ import annotations

from typing import TypeVar

from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn

SelfTrialOffPolicyAlgorithm = TypeVar("SelfTrialOffPolicyAlgorithm", bound="TrialOffPolicyAlgorithm")


class TrialOffPolicyAlgorithm(OffPolicyAlgorithm):
    """SB3's off-policy learn loop (collect, then update), with the number of updates after each
    rollout left to the algorithm (:meth:`_updates_due`).

    SB3 ties updates to ``train_freq`` calls of ``env.step``, so their rate per env step changes with
    ``n_envs``; the paper's algorithms update once per 4 env steps summed over all envs, which each
    algorithm counts in its own way (DREAM: env steps since the last update; RL2DQN: a fractional
    update budget that also honours ``gradient_steps`` and ``learning_starts``).
    """

    def _updates_due(self, rollout: RolloutReturn) -> int:
        """How many gradient steps to take after ``rollout`` (consumes what it returns)."""
        raise NotImplementedError

    def learn(
        self: SelfTrialOffPolicyAlgorithm,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "run",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTrialOffPolicyAlgorithm:
        """Train for ``total_timesteps`` env steps (summed over envs); ``log_interval`` counts trials."""
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        assert self.env is not None
        while self.num_timesteps < total_timesteps:
            rollout = self.collect_rollouts(
                self.env,
                callback=callback,
                train_freq=self.train_freq,  # type: ignore[arg-type]
                replay_buffer=self.replay_buffer,  # type: ignore[arg-type]
                action_noise=None,
                learning_starts=self.learning_starts,
                log_interval=log_interval,
            )
            if not rollout.continue_training:
                break
            n_updates = self._updates_due(rollout)
            if n_updates > 0:
                self.train(gradient_steps=n_updates, batch_size=self.batch_size)
        callback.on_training_end()
        return self
