"""The learn loop shared by the trial algorithms (RL2DQN, DREAM): SB3's, with the paper's update budget."""

from __future__ import annotations

from typing import Any, ClassVar, Dict, Iterable, Optional, Sequence, Tuple, Type, TypeVar, Union

import gymnasium as gym

from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.vec_env import VecEnv

from dream_envs.checks import check_non_negative, check_positive_int
from dream_envs.trial_env import check_trial_spec
from sb3_dream.common.files import PathOrFile, atomic_target

SelfTrialOffPolicyAlgorithm = TypeVar("SelfTrialOffPolicyAlgorithm", bound="TrialOffPolicyAlgorithm")


def trial_spec_of(env: Union[VecEnv, gym.Env]) -> Optional[Dict[str, Any]]:
    """The trial spec (:meth:`dream_envs.TrialEnv.trial_spec`) that every sub-env of ``env`` shares,
    or None where ``env`` is no trial env; a ``ValueError`` naming the setting where sub-envs differ
    (a VecEnv of mixed envs would train on sub-env 0's problems, horizon and trial length)."""
    if isinstance(env, VecEnv):
        if not env.has_attr("trial_spec"):
            return None
        specs = env.env_method("trial_spec")
    else:
        unwrapped = getattr(env, "unwrapped", env)
        if not hasattr(unwrapped, "trial_spec"):
            return None
        specs = [unwrapped.trial_spec()]
    for k, spec in enumerate(specs[1:], start=1):
        check_trial_spec(specs[0], spec, "sub-env 0 of the VecEnv", f"sub-env {k} of the VecEnv")
    return specs[0]


def check_tau(tau: Any) -> float:
    """SB3's target update coefficient: a number in [0, 1] (1: hard target updates), or a ``ValueError`` naming it."""
    if check_non_negative("tau", tau) > 1:
        raise ValueError(f"tau must be in [0, 1] (1: hard target updates), got {tau!r}")
    return float(tau)


def env_steps_per_update(train_freq: Union[int, Tuple[int, str]]) -> int:
    """``train_freq`` as env steps: an int, or SB3's ``(n, "step")`` form (episodes do not apply:
    one episode is a whole trial, and the paper counts updates per env step)."""
    if isinstance(train_freq, tuple):
        if len(train_freq) != 2 or train_freq[1] != "step":
            raise ValueError(f"train_freq must be an int or (n, 'step') (env steps per update), got {train_freq!r}")
        train_freq = train_freq[0]
    return check_positive_int("train_freq", train_freq, 1)


class TrialOffPolicyAlgorithm(OffPolicyAlgorithm):
    """SB3's off-policy loop (``collect_rollouts`` with the ``_sample_action``, ``_store_transition``
    and ``_on_step`` hooks, then ``train``), with the update budget of the paper's algorithms.

    SB3's argument names keep SB3's meaning:

    * ``learning_starts``: env steps, summed over the envs, before the first update;
    * ``train_freq``: env steps, summed over the envs, per round of updates, and
      ``gradient_steps``: updates per round. SB3 counts ``train_freq`` in calls of the vectorised
      ``env.step``, so its update rate per env step changes with ``n_envs``; the paper updates once
      every 4 env steps whatever the number of envs. So a rollout here is one vectorised step, and
      after each the rounds that are due (``train_freq`` env steps each) are run.

    SB3 arguments that do not apply to an algorithm raise an error naming its equivalent
    (:attr:`sb3_equivalents`); SB3's own numbers are checked (``learning_rate`` > 0, ``gamma`` in
    [0, 1], ...). ``save`` and ``save_replay_buffer`` are atomic.
    """

    #: SB3 constructor arguments the algorithm does not take, each with what to use instead.
    sb3_equivalents: ClassVar[Dict[str, str]] = {}

    def __init__(
        self,
        policy: Any,
        env: Any,
        learning_rate: Union[float, Schedule],
        *,
        learning_starts: int,
        train_freq: Union[int, Tuple[int, str]],
        gradient_steps: int,
        **kwargs: Any,
    ) -> None:
        if not callable(learning_rate) and check_non_negative("learning_rate", learning_rate) == 0:
            raise ValueError("learning_rate must be a number > 0 or a schedule, got 0")
        if check_non_negative("gamma", kwargs.get("gamma", 0.99)) > 1:
            raise ValueError(f"gamma must be in [0, 1], got {kwargs['gamma']!r}")
        check_positive_int("stats_window_size", kwargs.get("stats_window_size", 100), 1)
        check_positive_int("learning_starts", learning_starts, 0)
        check_positive_int("gradient_steps", gradient_steps, 0)
        self.train_every = env_steps_per_update(train_freq)
        self._steps_since_update = 0  # env steps not yet paid for by a round of updates
        super().__init__(
            policy,
            env,
            learning_rate,
            learning_starts=learning_starts,
            train_freq=TrainFreq(1, TrainFrequencyUnit.STEP),  # a rollout is one vectorised step
            gradient_steps=gradient_steps,
            **kwargs,
        )
        # The trial shape the model is built for (saved with it): checked against every env it meets.
        self.trial_spec = None if self.env is None else trial_spec_of(self.env)

    @classmethod
    def reject_sb3_arguments(cls, kwargs: Dict[str, Any]) -> None:
        """An error for keyword arguments the constructor does not take, naming the equivalent of
        SB3's where there is one."""
        for name in kwargs:
            if name in cls.sb3_equivalents:
                raise ValueError(f"{cls.__name__} does not take SB3's {name!r}: {cls.sb3_equivalents[name]}")
        if kwargs:
            raise TypeError(f"{cls.__name__}() got unexpected keyword arguments: {', '.join(sorted(kwargs))}")

    def _setup_model(self) -> None:
        super()._setup_model()
        # A rollout stays one vectorised step, also for a model saved with another train_freq.
        self.train_freq = TrainFreq(1, TrainFrequencyUnit.STEP)

    def check_trial_env(self, env: Union[VecEnv, gym.Env], what: str, ignore: Sequence[str] = ()) -> None:
        """A ``ValueError`` naming the setting and both values where ``env``'s trial spec differs
        from the model's (``ignore``: settings that may differ, e.g. ``n_exec_episodes`` at meta-test)."""
        spec = trial_spec_of(env)
        if spec is not None and self.trial_spec is not None:
            check_trial_spec(self.trial_spec, spec, "the model", what, ignore)

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``, after checking that ``env`` has the model's trial shape."""
        self.check_trial_env(env, "the env given to set_env")
        super().set_env(env, force_reset)

    @classmethod
    def load(  # type: ignore[override]
        cls: Type[SelfTrialOffPolicyAlgorithm],
        path: PathOrFile,
        env: Optional[GymEnv] = None,
        *args: Any,
        **kwargs: Any,
    ) -> SelfTrialOffPolicyAlgorithm:
        """SB3's ``load``; an ``env`` must have the saved model's trial shape."""
        model = super().load(path, env, *args, **kwargs)
        if env is not None:
            model.check_trial_env(model.get_env(), "the env given to load")
        return model

    def load_replay_buffer(self, path: PathOrFile, truncate_last_traj: bool = True) -> None:
        """SB3's ``load_replay_buffer``; the buffer must have been filled in the model's trial shape."""
        model_buffer = self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        try:
            self.check_replay_buffer(self.replay_buffer, path)
        except ValueError:
            self.replay_buffer = model_buffer
            raise

    def check_replay_buffer(self, buffer: Any, path: Any) -> None:
        """A ``ValueError`` naming the setting where ``buffer`` was filled in another trial shape."""
        spec = getattr(buffer, "trial_spec", None)
        if spec is not None and self.trial_spec is not None:
            check_trial_spec(self.trial_spec, spec, "the model", f"the replay buffer in {path}")

    def save(
        self, path: PathOrFile, exclude: Optional[Iterable[str]] = None, include: Optional[Iterable[str]] = None
    ) -> None:
        """SB3's ``save``, written to a temporary file beside ``path`` and renamed over it: a save
        that is interrupted leaves the previous file intact."""
        with atomic_target(path, "zip") as target:
            super().save(target, exclude, include)

    def save_replay_buffer(self, path: PathOrFile) -> None:
        """SB3's ``save_replay_buffer``, as atomic as :meth:`save`."""
        with atomic_target(path, "pkl") as target:
            super().save_replay_buffer(target)

    def _updates_due(self, n_env_steps: int) -> int:
        """Gradient steps owed after ``n_env_steps`` more env steps: ``gradient_steps`` per
        ``train_freq`` env steps once ``learning_starts`` env steps have passed."""
        if self.num_timesteps <= self.learning_starts:
            return 0
        self._steps_since_update += n_env_steps
        rounds = self._steps_since_update // self.train_every
        self._steps_since_update -= rounds * self.train_every
        return rounds * self.gradient_steps

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
            n_updates = self._updates_due(rollout.episode_timesteps)
            if n_updates > 0:
                self.train(gradient_steps=n_updates, batch_size=self.batch_size)
        callback.on_training_end()
        return self
