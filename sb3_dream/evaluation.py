"""Meta-test evaluation for any trial env and any agent (DREAM, RL2DQN, a scripted oracle).

A meta-test trial (paper, Section 2): in a problem of the chosen split, the agent explores for one
episode, then runs ``n_exec_episodes`` execution episodes; it is scored on the execution returns.
The problem ID never reaches the agent: scripted agents see only :func:`dream_envs.public_info`,
SB3 models only the observation.
"""

from __future__ import annotations

import csv
import os
import time
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

import dream_envs
from dream_envs import play_trials, play_trials_batched
from dream_envs.checks import check_choice, check_positive_int
from sb3_dream.common.agents import as_batch_trial_agent, as_trial_agent
from sb3_dream.common.files import atomic_target


@dataclass
class MetaEvalResult:
    """Execution returns of ``n_trials`` meta-test trials.

    ``returns[k, j]`` is trial k's return in execution episode j. With ``case_probabilities`` (an
    exhaustive evaluation, see :func:`evaluate_meta`) trial k played the split's (problem,
    instruction) pair ``k % n_cases`` in whole passes over the pairs, and every mean weights a pair
    by its probability: it is the split's expected return, not an estimate from drawn problems.
    """

    returns: np.ndarray
    exploration_lengths: np.ndarray
    problem_ids: np.ndarray
    seconds: float
    case_probabilities: Optional[np.ndarray] = None
    per_episode_mean: np.ndarray = field(init=False)
    per_episode_ci: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.per_episode_mean, self.per_episode_ci = self._mean_ci(self.returns)

    def _mean_ci(self, values: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Per column of ``values`` ``[n_trials, m]``: the mean and its 95% half-width.

        Drawn trials: the sample mean, normal approximation. Exhaustive: the probability-weighted
        mean; its only noise is each pair's spread over passes (a greedy agent in a deterministic
        env has none), so the half-width is ``1.96 * sqrt(sum_c p_c^2 s_c^2 / passes)`` from the
        passes' spread s_c, and NaN after a single pass (nothing to measure it with).
        """
        if self.case_probabilities is None:
            return values.mean(axis=0), _ci95(values)
        mean = self.trial_weights @ values  # each pair's probability, shared among its passes
        p = np.asarray(self.case_probabilities, dtype=np.float64)
        passes = values.reshape(-1, len(p), values.shape[1])  # [pass, case, m]
        if passes.shape[0] < 2:
            return mean, np.full(values.shape[1], np.nan)
        spread = passes.var(axis=0, ddof=1)  # [case, m]
        return mean, 1.96 * np.sqrt((p[:, None] ** 2 * spread).sum(axis=0) / passes.shape[0])

    @property
    def n_trials(self) -> int:
        return int(self.returns.shape[0])

    @property
    def exhaustive(self) -> bool:
        return self.case_probabilities is not None

    @property
    def trial_weights(self) -> np.ndarray:
        """Each trial's weight in :attr:`mean` ``[n_trials]`` (summing to 1): uniform, or its pair's
        probability over the number of passes when exhaustive."""
        if self.case_probabilities is None:
            return np.full(self.n_trials, 1.0 / self.n_trials)
        passes = self.n_trials // len(self.case_probabilities)
        return np.tile(np.asarray(self.case_probabilities, dtype=np.float64), passes) / passes

    @property
    def mean(self) -> float:
        """Mean execution return per episode, over all trials and execution episodes."""
        return float(self._mean_ci(self.returns.mean(axis=1, keepdims=True))[0][0])

    @property
    def ci(self) -> float:
        """95% confidence half-width of :attr:`mean` (normal approximation over trials; for an
        exhaustive evaluation see :meth:`_mean_ci`)."""
        return float(self._mean_ci(self.returns.mean(axis=1, keepdims=True))[1][0])

    @property
    def mean_exploration_length(self) -> float:
        return float(self._mean_ci(self.exploration_lengths.reshape(-1, 1))[0][0])

    def return_shares(self) -> Tuple[float, float, float]:
        """Shares of execution episodes whose return is above, below and at zero (weighted as
        :attr:`mean` is): where rewards are sparse and signed (SignNav3D's +1 for the right object,
        -1 for a wrong one, 0 for none) they tell a wrong choice from no choice, which a mean of 0
        does not."""
        signs = np.stack([self.returns > 0, self.returns < 0, self.returns == 0]).mean(axis=2)  # [3, n_trials]
        above, below, zero = signs @ self.trial_weights
        return float(above), float(below), float(zero)

    def summary(self) -> str:
        per_ep = ", ".join(format_mean_ci(m, c) for m, c in zip(self.per_episode_mean, self.per_episode_ci))
        trials = f"{self.n_trials} trials"
        if self.exhaustive:
            n_cases = len(self.case_probabilities)  # type: ignore[arg-type]
            passes = self.n_trials // n_cases
            over = f"over the split's {n_cases} (problem, instruction) pairs"
            trials += f" ({passes} pass{'es' if passes > 1 else ''} {over})"
        return (
            f"execution return {format_mean_ci(self.mean, self.ci)} over {trials} "
            f"(per episode: {per_ep}); exploration length {self.mean_exploration_length:.1f}"
        )


def format_mean_ci(mean: float, ci: float) -> str:
    """``mean ± ci``; the mean alone when ``ci`` is NaN (a single exhaustive pass measures none)."""
    return f"{mean:.3f}" if np.isnan(ci) else f"{mean:.3f} ± {ci:.3f}"


def _ci95(values: np.ndarray) -> np.ndarray:
    n = values.shape[0]
    if n < 2:
        return np.zeros(values.shape[1])
    return 1.96 * values.std(axis=0, ddof=1) / np.sqrt(n)


def exhaustive_cases(env: gym.Env, split: str, n_trials: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pinned trials of an exhaustive evaluation of ``split``: every (problem, instruction) pair
    of :meth:`dream_envs.TrialEnv.trial_cases`, in whole passes, at least ``n_trials`` trials.
    Returns ``(problem_ids, instructions, probabilities)`` of one pass; play
    ``len(problem_ids) * passes`` trials with them cycled."""
    trial_env = env.unwrapped
    try:
        problem_ids, instructions, probabilities = trial_env.trial_cases(split)
    except NotImplementedError as err:
        raise ValueError(f"exhaustive=True needs a trial env that lists its instructions: {err}") from None
    passes = -(-check_positive_int("n_trials", n_trials) // len(problem_ids))
    return np.tile(problem_ids, passes), np.tile(instructions, (passes, 1)), probabilities


def _make_env(env: Union[str, gym.Env], split: str, n_exec_episodes: int, env_kwargs: Optional[dict]) -> gym.Env:
    if isinstance(env, str):
        return gym.make(env, split=split, n_exec_episodes=n_exec_episodes, **(env_kwargs or {}))
    unwrapped = env.unwrapped
    if not isinstance(unwrapped, dream_envs.TrialEnv):
        raise TypeError(f"env must be a trial env (dream_envs.TrialEnv) or its ID, got {type(unwrapped).__name__}")
    check_choice("split", split, unwrapped.splits)
    if unwrapped.split != split or unwrapped.n_exec_episodes != n_exec_episodes:
        raise ValueError(
            f"env has split={unwrapped.split!r}, n_exec_episodes={unwrapped.n_exec_episodes} but "
            f"split={split!r}, n_exec_episodes={n_exec_episodes} were asked for: pass an env ID or a matching env"
        )
    return env


EnvArgument = Union[str, gym.Env, Sequence[gym.Env]]


def make_envs(
    env: EnvArgument, split: str, n_exec_episodes: int, env_kwargs: Optional[dict], n_envs: int
) -> Tuple[List[gym.Env], List[gym.Env]]:
    """The trial envs to play in and those of them made here (the caller closes them): an ID is
    made ``n_envs`` times, a list of envs or a single env is used as given (an env's wrappers
    cannot be copied faithfully: pass a list to play trials side by side in it)."""
    if isinstance(env, str):
        envs = [_make_env(env, split, n_exec_episodes, env_kwargs) for _ in range(n_envs)]
        return envs, list(envs)
    if isinstance(env, (list, tuple)):
        if len(env) == 0:
            raise ValueError("env must not be an empty list of envs")
        return [_make_env(e, split, n_exec_episodes, None) for e in env], []
    return [_make_env(env, split, n_exec_episodes, None)], []


def trial_problem_ids(
    split_ids: Sequence[int], n_trials: int, seed: int = 0, problem_ids: Optional[Sequence[int]] = None
) -> np.ndarray:
    """The problem of each of ``n_trials`` trials, as the diagnostics (DREAM's and IMPORT's
    ``diagnose``) play them: ``problem_ids`` cycled, or by default drawn uniformly from
    ``split_ids`` with ``seed``. Hand the result to a privileged agent and to the trial runner
    (``problem_ids=``) to play the same trials."""
    if problem_ids is None:
        return np.random.default_rng(seed).choice(np.asarray(split_ids), size=n_trials)
    if len(problem_ids) == 0:
        raise ValueError("problem_ids must not be empty")
    return np.resize(np.asarray(problem_ids, dtype=np.int64), n_trials)


@dataclass
class PrivilegedTrials:
    """The trials of a diagnostic that hands its agent each trial's problem: made by
    :func:`privileged_trials`, played by :meth:`play` as many times as the diagnostic has agents
    (the same trials each time), closed by :meth:`close` or a ``with`` block.

    ``problem_ids[k]`` is trial k's problem; ``split_ids`` the split's problem IDs.
    """

    envs: List[gym.Env]
    made: List[gym.Env]  # the envs made here, which :meth:`close` closes
    split_ids: np.ndarray
    problem_ids: np.ndarray
    split: str
    seed: int
    exhaustive: bool

    def play(self, agent: Any) -> MetaEvalResult:
        """:func:`evaluate_meta` of ``agent`` on these trials, side by side over the envs."""
        return evaluate_meta(
            agent,
            self.envs,
            len(self.problem_ids),
            self.split,
            seed=self.seed,
            # exhaustive: evaluate_meta pins the same pairs itself
            problem_ids=None if self.exhaustive else self.problem_ids,
            n_envs=len(self.envs),
            exhaustive=self.exhaustive,
        )

    def close(self) -> None:
        for env in self.made:
            env.close()

    def __enter__(self) -> "PrivilegedTrials":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def privileged_trials(
    env: Union[str, gym.Env],
    n_trials: int,
    split: str,
    seed: int,
    env_kwargs: Optional[Dict[str, Any]],
    problem_ids: Optional[Sequence[int]],
    n_envs: int,
    exhaustive: bool = False,
) -> PrivilegedTrials:
    """Checks the arguments of a diagnostic that hands its agent each trial's problem, makes the
    envs and draws the trials' problems. ``exhaustive``: trial k's problem is that of the split's
    (problem, instruction) pair k (cycled, whole passes, as :func:`evaluate_meta` pins them)."""
    n_trials = check_positive_int("n_trials", n_trials)
    n_envs = check_positive_int("n_envs", n_envs)
    if exhaustive and problem_ids is not None:
        raise ValueError("problem_ids and exhaustive=True both pin the trials' problems: pass one of them")
    envs, made = make_envs(env, split, 1, env_kwargs, n_envs if exhaustive else min(n_envs, n_trials))
    split_ids = np.asarray(envs[0].unwrapped.problem_ids(split))  # the envs checked ``split``
    if exhaustive:
        trial_problems = exhaustive_cases(envs[0], split, n_trials)[0]
    else:
        trial_problems = trial_problem_ids(split_ids, n_trials, seed, problem_ids)
    return PrivilegedTrials(envs, made, split_ids, np.asarray(trial_problems), split, seed, exhaustive)


def evaluate_meta(
    agent: Any,
    env: EnvArgument,
    n_trials: int = 100,
    split: str = "test",
    n_exec_episodes: int = 1,
    deterministic: bool = True,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    env_kwargs: Optional[Dict[str, Any]] = None,
    n_envs: int = 16,
    exhaustive: bool = False,
) -> MetaEvalResult:
    """Run ``n_trials`` meta-test trials of ``agent`` on ``split`` and collect execution returns.

    :param agent: a :class:`dream_envs.ScriptedAgent`, a :class:`dream_envs.BatchTrialAgent` or a model
        with ``predict`` (RL2DQN, DREAM).
    :param env: an env ID (made ``n_envs`` times with ``split``, ``n_exec_episodes`` and
        ``env_kwargs``), a trial env already made with that split and number of execution episodes,
        or a list of such envs (trials are played side by side in at most ``n_envs`` of them).
    :param problem_ids: if given, trial k is pinned to ``problem_ids[k % len(problem_ids)]`` (for an
        exhaustive evaluation); otherwise problems are drawn from the split, reproducibly from ``seed``.
    :param n_envs: trials played side by side, one batched forward per step, by a model (a scripted
        agent plays one at a time). Trial k is seeded ``seed + k`` either way, so a greedy model
        plays the same trials with any ``n_envs`` (up to the rounding of batched matrix products).
    :param exhaustive: play every (problem, instruction) pair of ``split`` pinned, in whole passes
        (at least ``n_trials`` trials: MetaCook's held-out split has 133 pairs, so ``n_trials=100``
        plays one pass), and weight each by its probability under the split's sampling
        (:meth:`dream_envs.TrialEnv.trial_cases`). The mean is then the split's expected return
        itself: exact for a greedy agent in a deterministic env, where 100 drawn trials swing with
        which problems and instructions the draw holds. Each execution episode of a trial gets the
        pair's instruction, so with ``n_exec_episodes > 1`` an agent whose episodes depend on each
        other (RL²) is scored on repeats of one instruction.
    """
    n_trials = check_positive_int("n_trials", n_trials)
    n_exec_episodes = check_positive_int("n_exec_episodes", n_exec_episodes)
    n_envs = check_positive_int("n_envs", n_envs)
    if exhaustive and problem_ids is not None:
        raise ValueError("problem_ids and exhaustive=True both pin the trials' problems: pass one of them")
    batch_agent = as_batch_trial_agent(agent, deterministic) if n_envs > 1 else None
    side_by_side = (n_envs if exhaustive else min(n_envs, n_trials)) if batch_agent is not None else 1
    envs, made = make_envs(env, split, n_exec_episodes, env_kwargs, side_by_side)
    envs = envs[:side_by_side]
    if hasattr(agent, "check_trial_env"):  # a model evaluated in another trial shape acts on garbage
        try:
            for e in envs:  # more execution episodes per trial than in training is a meta-test choice
                agent.check_trial_env(e, "the evaluation env", ignore=("n_exec_episodes",))
        except ValueError:
            for e in made:
                e.close()
            raise
    instructions, probabilities = None, None
    if exhaustive:
        problem_ids, instructions, probabilities = exhaustive_cases(envs[0], split, n_trials)
        n_trials = len(problem_ids)

    start = time.perf_counter()
    if batch_agent is not None and len(envs) > 1:
        trials: Iterable[Dict[str, Any]] = play_trials_batched(
            envs, batch_agent, n_trials, seed, problem_ids, instructions
        )
    else:
        trials = play_trials(envs[0], as_trial_agent(agent, deterministic), n_trials, seed, problem_ids, instructions)
    returns, lengths, pids = [], [], []
    for result in trials:
        returns.append(result["execution_returns"])
        lengths.append(result["exploration_length"])
        pids.append(result["problem_id"])
    for e in made:
        e.close()
    return MetaEvalResult(
        returns=np.asarray(returns, dtype=np.float64),
        exploration_lengths=np.asarray(lengths, dtype=np.float64),
        problem_ids=np.asarray(pids, dtype=np.int64),
        seconds=time.perf_counter() - start,
        case_probabilities=probabilities,
    )


BEST_TIES = ("first", "last")
CURVE_COLUMNS = ("env_steps", "wall_clock_s", "mean", "ci", "exploration_length")


class MetaEvalCallback(BaseCallback):
    """Runs :func:`evaluate_meta` every ``eval_freq`` env steps during training and logs it.

    Logger keys: ``eval/execution_return`` (mean over trials and execution episodes),
    ``eval/execution_return_ci``, ``eval/execution_return_ep{j}`` for j >= 1 when
    ``n_exec_episodes > 1``, ``eval/exploration_length`` (``eval/`` is ``log_prefix``). With
    ``csv_path`` it also appends a row ``env_steps, wall_clock_s, mean, ci, exploration_length``
    per evaluation (a learning curve).

    :param eval_freq: evaluate every this many env steps (counted over all envs), and once at the
        start and the end of training.
    :param n_envs: copies of the eval env (when given as an ID), made once, in which trials are
        played side by side (see :func:`evaluate_meta`).
    :param best_model_save_path: as in SB3's ``EvalCallback``: a folder where the model is saved as
        ``best_model.zip`` each time its mean execution return beats every earlier evaluation
        (``best_mean_reward``, reached at ``best_env_steps``). Training swings, so this keeps the best
        model seen; select it on a split the agent trains on (``split="train"``), so that its
        held-out return stays an honest estimate.
    :param best_ties: which of several evaluations with the same best return keeps the model:
        ``"first"`` (SB3's ``EvalCallback``: a later one must beat it) or ``"last"`` (the latest of
        them). On a split the agent saturates (e.g. at the oracle's return) the first is an early model; the
        latest has trained longest.
    :param exhaustive: every evaluation plays all of the split's (problem, instruction) pairs and
        weights them by their probability (see :func:`evaluate_meta`): the curve then shows the
        split's expected return, not a 100-trial draw's (``n_trials`` is then a minimum: whole
        passes over the pairs). The CSV's ``ci`` is NaN after a single pass.
    :param log_prefix: the start of its logger keys (default ``"eval/"``, SB3's ``EvalCallback``'s):
        callbacks that evaluate different splits of one model need different ones, e.g.
        ``"eval_train/"`` for the training split, or each overwrites the other's values.
    """

    def __init__(
        self,
        eval_env: EnvArgument,
        eval_freq: int = 10_000,
        n_trials: int = 100,
        split: str = "test",
        n_exec_episodes: int = 1,
        deterministic: bool = True,
        seed: int = 0,
        env_kwargs: Optional[Dict[str, Any]] = None,
        csv_path: Optional[str] = None,
        best_model_save_path: Optional[str] = None,
        n_envs: int = 16,
        best_ties: str = "first",
        exhaustive: bool = False,
        log_prefix: str = "eval/",
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.best_ties = check_choice("best_ties", best_ties, BEST_TIES)
        if not isinstance(log_prefix, str) or not log_prefix:
            raise ValueError(f"log_prefix must be a non-empty string such as 'eval/', got {log_prefix!r}")
        self.log_prefix = log_prefix
        self.eval_freq = check_positive_int("eval_freq", eval_freq)
        self.n_trials = check_positive_int("n_trials", n_trials)
        self.n_exec_episodes = check_positive_int("n_exec_episodes", n_exec_episodes)
        n_envs = check_positive_int("n_envs", n_envs)
        # made once: the trials of every evaluation are played side by side in these copies
        n_side = n_envs if exhaustive else min(n_envs, self.n_trials)
        self.eval_envs, _ = make_envs(eval_env, split, n_exec_episodes, env_kwargs, n_side)  # they check ``split``
        self.exhaustive = bool(exhaustive)
        if self.exhaustive:
            exhaustive_cases(self.eval_envs[0], split, self.n_trials)  # fails now, not at the first evaluation
        self.eval_env = self.eval_envs[0]
        self.split = split
        self.deterministic, self.seed, self.csv_path = deterministic, seed, csv_path
        self.best_model_save_path = best_model_save_path
        self.best_mean_reward = -np.inf
        self.best_env_steps: Optional[int] = None
        self.results: List[Dict[str, float]] = []
        self._last_eval_step: Optional[int] = None
        self._train_start = time.perf_counter()
        self._wall_clock_offset = 0.0

    def resume(self, results: List[Dict[str, float]]) -> None:
        """Continue the learning curve of an interrupted run (its rows up to the checkpoint it resumes
        from): the CSV is rewritten with them, wall-clock goes on from the last one, and the start
        of training evaluates only if the model has moved past the last row."""
        self.results = [dict(row) for row in results]
        if self.results:
            self._last_eval_step = int(self.results[-1]["env_steps"])
            self._wall_clock_offset = float(self.results[-1]["wall_clock_s"])
            for row in self.results:
                if self._is_best(float(row["mean"])):
                    self.best_mean_reward, self.best_env_steps = float(row["mean"]), int(row["env_steps"])
        if self.csv_path:
            os.makedirs(os.path.dirname(os.path.abspath(self.csv_path)), exist_ok=True)
            with open(self.csv_path, "w", newline="") as f:
                writer = csv.writer(f)
                writer.writerow(CURVE_COLUMNS)
                writer.writerows([row[k] for k in CURVE_COLUMNS] for row in self.results)

    def _is_best(self, mean: float) -> bool:
        """Whether an evaluation's mean return takes the best model's place (see ``best_ties``)."""
        return mean > self.best_mean_reward or (self.best_ties == "last" and mean == self.best_mean_reward)

    def _on_training_start(self) -> None:
        self._train_start = time.perf_counter()
        if self.csv_path:
            os.makedirs(os.path.dirname(os.path.abspath(self.csv_path)), exist_ok=True)
            if not os.path.exists(self.csv_path):
                with open(self.csv_path, "w", newline="") as f:
                    csv.writer(f).writerow(CURVE_COLUMNS)
        if self._last_eval_step != self.num_timesteps:
            self._evaluate()

    def _on_step(self) -> bool:
        if self.num_timesteps - (self._last_eval_step or 0) >= self.eval_freq:
            self._evaluate()
        return True

    def _on_training_end(self) -> None:
        if self._last_eval_step != self.num_timesteps:
            self._evaluate()

    def _evaluate(self) -> None:
        wall_clock = self._wall_clock_offset + time.perf_counter() - self._train_start
        result = evaluate_meta(
            self.model,
            self.eval_envs,
            n_trials=self.n_trials,
            split=self.split,
            n_exec_episodes=self.n_exec_episodes,
            deterministic=self.deterministic,
            seed=self.seed,
            n_envs=len(self.eval_envs),
            exhaustive=self.exhaustive,
        )
        self._last_eval_step = self.num_timesteps
        row = {
            "env_steps": self.num_timesteps,
            "wall_clock_s": wall_clock,
            "mean": result.mean,
            "ci": result.ci,
            "exploration_length": result.mean_exploration_length,
        }
        self.results.append(row)
        key = self.log_prefix
        self.logger.record(f"{key}execution_return", result.mean)
        self.logger.record(f"{key}execution_return_ci", result.ci)
        self.logger.record(f"{key}exploration_length", result.mean_exploration_length)
        if self.n_exec_episodes > 1:
            for j, m in enumerate(result.per_episode_mean, start=1):
                self.logger.record(f"{key}execution_return_ep{j}", float(m))
        self.logger.dump(self.num_timesteps)
        if self._is_best(result.mean):
            self.best_mean_reward, self.best_env_steps = float(result.mean), int(self.num_timesteps)
            if self.best_model_save_path is not None:
                # atomic for any SB3 model: a reader never sees half a model
                with atomic_target(os.path.join(self.best_model_save_path, "best_model.zip"), "zip") as tmp:
                    self.model.save(tmp)
        if self.csv_path:
            with open(self.csv_path, "a", newline="") as f:
                csv.writer(f).writerow([row[k] for k in CURVE_COLUMNS])
        if self.verbose:
            print(f"[{self.num_timesteps} steps, {wall_clock:.0f}s] {self.split}: {result.summary()}")
