"""The trial API: turn an instruction-based meta-RL (IMRL) problem family into Gymnasium episodes.

One Gymnasium episode is one *trial* (paper, Section 2 and 3): in a problem T drawn from a
split, the agent plays one exploration episode (reward-free and instruction-free by default),
then ``n_exec_episodes`` execution episodes, each with a freshly sampled instruction i and
rewards R_T(s, i). ``terminated`` ends the trial.

A new meta-RL environment subclasses :class:`TrialEnv` and defines the problem family:

* the problem set and its splits: :meth:`TrialEnv._split_problem_ids`;
* the instructions of a problem: :meth:`TrialEnv._instruction_choices`, drawn uniformly (or
  another distribution: :meth:`TrialEnv._sample_instruction`), and optionally
  :meth:`TrialEnv._check_instruction` for pinned instructions;
* the inner MDP given (problem, instruction): :meth:`TrialEnv._set_problem`,
  :meth:`TrialEnv._inner_reset`, :meth:`TrialEnv._inner_step` and optionally
  :meth:`TrialEnv._end_episode_reward`;
* a picture: :meth:`TrialEnv._render_frame`.

Everything else (the Dict observation, the ``info`` keys, pinning through ``reset(options=...)``,
seeding, horizons, the end-episode action, validation of the arguments) lives here, so every
env obeys the same contract (see the project's design notes):

Observation (a ``gymnasium.spaces.Dict``):

=================  ===========================================================================
``obs``            the inner state of the problem family
``instruction``    MultiDiscrete; all zeros (the reserved "none" value) in reward-free exploration
``phase``          Discrete(2): 0 exploration episode, 1 execution episode
``episode_start``  Discrete(2): 1 on the first step of each inner episode
``prev_action``    Discrete(n_actions + 1): 0 at the trial's start, else the previous action + 1
``prev_reward``    Box(1,) float32: the previous step's reward (0 in reward-free exploration)
=================  ===========================================================================

``prev_action`` and ``prev_reward`` carry across inner-episode boundaries (the first step of an
execution episode sees the last action and reward of the episode before), as in RL²; they are
zero only at the start of a trial.

``info`` holds, at reset and after every step: ``problem_id`` (privileged: never in the
observation), ``phase`` and ``episode_index`` (0 exploration, 1..N execution) of the episode that
the returned observation belongs to. On the last step of an inner episode it also holds
``episode_end=True``, ``episode_return``, ``episode_length``, ``episode_phase``,
``episode_truncated`` (ended by the horizon, not by the MDP or the end-episode action) and ``final_obs``
(that episode's last inner ``obs``: the step already returns the next episode's first
observation); with ``final_frames=True`` (which needs ``render_mode="rgb_array"``) also
``final_frame``, :meth:`render`'s picture of that last state. On the trial's last step it holds
``execution_returns``, the list of the N execution returns.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Dict, Optional, Sequence, SupportsFloat, Tuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from dream_envs.checks import check_action, check_bool, check_choice, check_positive_int

# Every family has these splits; a family may add its own (``TrialEnv.splits``, e.g. MetaCook's).
SPLITS = ("train", "test", "all")
EXPLORATION, EXECUTION = 0, 1


class TrialEnv(gym.Env, ABC):
    """Base class of the IMRL trial environments.

    :param inner_observation_space: the space of the inner state ``obs``.
    :param instruction_nvec: sizes of the instruction's dimensions (value 0 of each means "none").
    :param n_actions: number of actions (``Discrete(n_actions)``).
    :param end_episode_action: the action that ends the current inner episode at once
        (the paper's a_term), or ``None`` if the family has none.
    :param split: which problems (and instructions) are sampled: "train", "test" or "all", or one of
        the family's own :attr:`splits`.
    :param n_exec_episodes: the number N of execution episodes per trial.
    :param horizon: the inner-episode horizon (steps per exploration or execution episode).
    :param reward_free_exploration: if True (the paper's IMRL setting) the exploration episode has
        no instruction and no rewards; if False it gets an instruction and its rewards (the paper's
        "dashed line" variant), which then count in the step rewards and so in the trial's return.
    :param render_mode: ``None`` or ``"rgb_array"``.
    :param final_frames: if True, ``info["final_frame"]`` holds :meth:`render`'s picture of each
        inner episode's last state (the step already returns the next episode's start); needs
        ``render_mode="rgb_array"``. Off by default because Stable-Baselines3 makes every env it
        builds from an ID (``make_vec_env``, ``DREAM("MetaBus-v0")``) with ``render_mode="rgb_array"``
        so that videos can be recorded, and drawing a picture costs far more than a step.
    :param reward_bound: a bound on the absolute value of one step's reward (the bounds of
        ``prev_reward``).
    """

    metadata: Dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 4}
    splits: Tuple[str, ...] = SPLITS
    """The splits this family offers: always "train", "test" and "all", then any of its own."""
    action_names: Optional[Tuple[str, ...]] = None
    """A short name per action, for reports (e.g. ``examples/meta_test.py --trace``); None: numbers."""

    def __init__(
        self,
        *,
        inner_observation_space: spaces.Space,
        instruction_nvec: Sequence[int],
        n_actions: int,
        end_episode_action: Optional[int],
        split: str = "train",
        n_exec_episodes: int = 1,
        horizon: int = 20,
        reward_free_exploration: bool = True,
        render_mode: Optional[str] = None,
        final_frames: bool = False,
        reward_bound: float = 10.0,
    ) -> None:
        super().__init__()
        self.split = check_choice("split", split, self.splits)
        self.n_exec_episodes = check_positive_int("n_exec_episodes", n_exec_episodes)
        self.horizon = check_positive_int("horizon", horizon)
        self.reward_free_exploration = check_bool("reward_free_exploration", reward_free_exploration)
        self.render_mode = check_choice("render_mode", render_mode, [None, *self.metadata["render_modes"]])
        self.final_frames = check_bool("final_frames", final_frames)
        if self.final_frames and self.render_mode != "rgb_array":
            raise ValueError(f"final_frames=True needs render_mode='rgb_array', got render_mode={render_mode!r}")
        self.n_actions = int(n_actions)
        self.end_episode_action = end_episode_action
        self.instruction_nvec = np.asarray(instruction_nvec, dtype=np.int64)

        self.inner_observation_space = inner_observation_space
        self.observation_space = spaces.Dict(
            {
                "obs": inner_observation_space,
                "instruction": spaces.MultiDiscrete(self.instruction_nvec),
                "phase": spaces.Discrete(2),
                "episode_start": spaces.Discrete(2),
                "prev_action": spaces.Discrete(self.n_actions + 1),
                "prev_reward": spaces.Box(-reward_bound, reward_bound, shape=(1,), dtype=np.float32),
            }
        )
        self.action_space = spaces.Discrete(self.n_actions)

        self.problem_id: Optional[int] = None
        self.instruction: Optional[np.ndarray] = None  # None while exploring reward-free
        self._pinned_instruction: Optional[np.ndarray] = None
        self._inner_obs: Optional[np.ndarray] = None
        self._needs_reset = True

    # ------------------------------------------------------------------ the problem family
    @property
    @abstractmethod
    def n_problems(self) -> int:
        """Number of problem IDs (IDs are 0 .. n_problems - 1); sizes a problem-ID embedding."""

    @abstractmethod
    def _split_problem_ids(self, split: str) -> np.ndarray:
        """The sorted problem IDs of ``split`` (one of :attr:`splits`)."""

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        """``[n, len(instruction_nvec)]``: the instructions of ``problem_id`` in ``split``, which
        :meth:`_sample_instruction` draws uniformly. A family defines this, or overrides
        :meth:`_sample_instruction` for another distribution (it then cannot be evaluated
        exhaustively, see :meth:`trial_cases`)."""
        raise NotImplementedError(
            f"{type(self).__name__} does not list its instructions: define _instruction_choices(problem_id, split)"
        )

    def _sample_instruction(self, problem_id: int, split: str) -> np.ndarray:
        """Draw an instruction for ``problem_id`` with ``self.np_random`` (respecting held-out ones):
        uniformly among :meth:`_instruction_choices` (no draw when there is one)."""
        choices = self._instruction_choices(problem_id, split)
        return choices[int(self.np_random.integers(len(choices)))] if len(choices) > 1 else choices[0]

    def _check_instruction(self, problem_id: int, instruction: np.ndarray) -> None:
        """Raise ``ValueError`` if a pinned ``instruction`` is not valid for ``problem_id``."""

    @abstractmethod
    def _set_problem(self, problem_id: int) -> None:
        """Build the problem's MDP (e.g. which bus goes where)."""

    @abstractmethod
    def _inner_reset(self) -> np.ndarray:
        """Start an inner episode in the current problem; return its first inner ``obs``.

        ``self.instruction`` is the episode's instruction (``None`` in reward-free exploration)."""

    @abstractmethod
    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        """One inner step (never the end-episode action): return ``(obs, reward, done)``.

        The reward is R_T(s, i) for ``self.instruction``; ``done`` says the instruction is
        fulfilled. With ``self.instruction is None`` (reward-free exploration) return reward 0
        and ``done=False``."""

    def _end_episode_reward(self, steps_remaining: int) -> float:
        """Reward of the end-episode action when ``steps_remaining`` steps (this one included) were left."""
        return 0.0

    @abstractmethod
    def _render_frame(self) -> np.ndarray:
        """An HxWx3 uint8 picture of the current state."""

    @property
    def problem_nvec(self) -> np.ndarray:
        """Sizes of the dimensions of :meth:`problem_features` (default: the bare ID)."""
        return np.array([self.n_problems], dtype=np.int64)

    def problem_features(self, problem_id: int) -> np.ndarray:
        """The problem's structured representation (paper, Appendix B.1: e.g. cooking's fridge triple).

        A problem-ID encoder embeds each dimension separately (Appendix B.3), so held-out problems
        share parts with training ones. Default: the bare ID. Values lie in ``[0, problem_nvec)``.
        """
        return np.array([problem_id], dtype=np.int64)

    # ------------------------------------------------------------------ public helpers
    def problem_feature_table(self) -> np.ndarray:
        """``[n_problems, len(problem_nvec)]``: :meth:`problem_features` of every problem ID."""
        return np.stack([self.problem_features(k) for k in range(self.n_problems)]).astype(np.int64)

    def trial_spec(self) -> Dict[str, Any]:
        """The trial shape a model trained in this env relies on: the problem family and how its
        problems are represented, the inner-episode horizon, the execution episodes per trial,
        the splits' sizes (the split an env samples from is not part of it) and whether the
        exploration episode is reward-free (a model trained with an instruction and rewards there,
        the paper's dashed lines, reads them in its inputs). The algorithms check
        it with :func:`check_trial_spec`: a VecEnv's sub-envs against each other, a model against
        the env it is given."""
        return {
            "family": type(self).__name__,
            "horizon": int(self.horizon),
            "n_exec_episodes": int(self.n_exec_episodes),
            "n_problems": int(self.n_problems),
            "problem_nvec": [int(n) for n in self.problem_nvec],
            "split_sizes": {split: len(self._split_problem_ids(split)) for split in self.splits},
            "reward_free_exploration": bool(self.reward_free_exploration),
        }

    def problem_ids(self, split: Optional[str] = None) -> np.ndarray:
        """The problem IDs of ``split`` (default: this env's split)."""
        split = self.split if split is None else check_choice("split", split, self.splits)
        return np.asarray(self._split_problem_ids(split), dtype=np.int64)

    def instruction_choices(self, problem_id: int, split: Optional[str] = None) -> np.ndarray:
        """``[n, len(instruction_nvec)]``: the instructions a trial of ``problem_id`` in ``split``
        (default: this env's split) draws uniformly for each execution episode."""
        split = self.split if split is None else check_choice("split", split, self.splits)
        return np.asarray(self._instruction_choices(int(problem_id), split), dtype=np.int64).reshape(
            -1, len(self.instruction_nvec)
        )

    def trial_cases(self, split: Optional[str] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (problem, instruction) pair a trial of ``split`` (default: this env's split) can
        start with, and its probability: ``(problem_ids [n], instructions [n, d], probabilities [n])``.

        A problem is drawn uniformly from the split, then an instruction uniformly from the
        problem's, so a pair's probability is ``1 / (n_problems_in_split * n_its_instructions)``.
        Playing each pair pinned (``reset(options={"problem_id": k, "instruction": i})``) and
        weighting by these probabilities gives the split's expected return without the noise of
        drawing problems (:func:`sb3_dream.evaluate_meta` with ``exhaustive=True``).
        """
        split = self.split if split is None else check_choice("split", split, self.splits)
        problem_ids = self.problem_ids(split)
        pids, instructions, probabilities = [], [], []
        for k in problem_ids:
            choices = self.instruction_choices(int(k), split)
            pids.extend([int(k)] * len(choices))
            instructions.append(choices)
            probabilities.extend([1.0 / (len(problem_ids) * len(choices))] * len(choices))
        return (
            np.asarray(pids, dtype=np.int64),
            np.concatenate(instructions).astype(np.int64),
            np.asarray(probabilities, dtype=np.float64),
        )

    @property
    def phase(self) -> int:
        return EXPLORATION if self.episode_index == 0 else EXECUTION

    # ------------------------------------------------------------------ Gymnasium API
    def reset(
        self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None
    ) -> tuple[Dict[str, Any], Dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"problem_id", "instruction"}
        if unknown:
            raise ValueError(f"options has unknown keys {sorted(unknown)}; accepted keys: 'problem_id', 'instruction'")

        if options.get("problem_id") is not None:
            problem_id = options["problem_id"]
            if (
                isinstance(problem_id, (bool, np.bool_))
                or not isinstance(problem_id, (int, np.integer))
                or not 0 <= problem_id < self.n_problems
            ):
                raise ValueError(
                    f"options['problem_id']={problem_id!r} is out of range: "
                    f"accepted values are integers 0 .. {self.n_problems - 1}"
                )
            self.problem_id = int(problem_id)
        else:
            self.problem_id = int(self.np_random.choice(self.problem_ids()))
        self._set_problem(self.problem_id)

        self._pinned_instruction = None
        if options.get("instruction") is not None:
            self._pinned_instruction = self._validate_instruction(options["instruction"])

        self.episode_index = 0
        self._prev_action = 0
        self._prev_reward = 0.0
        self._execution_returns: list[float] = []
        self._start_inner_episode()
        self._needs_reset = False
        return self._observation(), self._info()

    def step(self, action: Any) -> tuple[Dict[str, Any], SupportsFloat, bool, bool, Dict[str, Any]]:
        if self._needs_reset:
            raise RuntimeError("step() called before reset() or after the trial terminated; call reset() first")
        action = check_action(action, self.n_actions)

        steps_remaining = self.horizon - self._t
        if action == self.end_episode_action:
            reward, done = self._end_episode_reward(steps_remaining), True
        else:
            self._inner_obs, reward, done = self._inner_step(action)
        if self.instruction is None:
            reward = 0.0  # reward-free exploration
        reward = float(reward)
        self._t += 1
        self._episode_return += reward
        self._prev_action, self._prev_reward = action + 1, reward

        terminated = False
        end_info: Dict[str, Any] = {}
        if done or self._t >= self.horizon:
            end_info = {
                "episode_end": True,
                # ended by the horizon alone (a time limit: the last state is not terminal)
                "episode_truncated": not done,
                "episode_return": self._episode_return,
                "episode_length": self._t,
                "episode_phase": self.phase,
                "final_obs": np.array(self._inner_obs, copy=True),
            }
            if self.final_frames:  # render() will show the next episode's start
                end_info["final_frame"] = self._render_frame()
            if self.phase == EXECUTION:
                self._execution_returns.append(self._episode_return)
            if self.episode_index == self.n_exec_episodes:
                terminated = True
                self._needs_reset = True
                end_info["execution_returns"] = list(self._execution_returns)
            else:
                self.episode_index += 1
                self._start_inner_episode()
        info = self._info()
        info.update(end_info)
        return self._observation(), reward, terminated, False, info

    def render(self) -> Optional[np.ndarray]:
        if self.render_mode == "rgb_array":
            if self.problem_id is None:
                raise RuntimeError("render() needs a trial: call reset() first")
            return self._render_frame()
        return None

    # ------------------------------------------------------------------ internals
    def _validate_instruction(self, instruction: Any) -> np.ndarray:
        arr = np.asarray(instruction)
        ok = (
            arr.shape == self.instruction_nvec.shape
            and np.issubdtype(arr.dtype, np.integer)
            and bool(np.all(arr >= 1))
            and bool(np.all(arr < self.instruction_nvec))
        )
        if not ok:
            ranges = ", ".join(f"1..{n - 1}" for n in self.instruction_nvec)
            raise ValueError(
                f"options['instruction']={instruction!r} is not valid: expected {len(self.instruction_nvec)} "
                f"integer(s) in [{ranges}] (0 means 'none' and cannot be pinned)"
            )
        arr = arr.astype(np.int64)
        self._check_instruction(self.problem_id, arr)
        return arr

    def _start_inner_episode(self) -> None:
        if self.phase == EXPLORATION and self.reward_free_exploration:
            self.instruction = None
        elif self._pinned_instruction is not None:
            self.instruction = self._pinned_instruction.copy()
        else:
            self.instruction = np.asarray(self._sample_instruction(self.problem_id, self.split), dtype=np.int64)
        self._t = 0
        self._episode_return = 0.0
        self._inner_obs = self._inner_reset()

    def _observation(self) -> Dict[str, Any]:
        instruction = np.zeros_like(self.instruction_nvec) if self.instruction is None else self.instruction.copy()
        episode_start = int(self._t == 0)
        return {
            "obs": np.array(self._inner_obs, copy=True),
            "instruction": instruction,
            "phase": self.phase,
            "episode_start": episode_start,
            "prev_action": self._prev_action,
            "prev_reward": np.array([self._prev_reward], dtype=np.float32),
        }

    def _info(self) -> Dict[str, Any]:
        return {"problem_id": self.problem_id, "phase": self.phase, "episode_index": self.episode_index}


def check_trial_spec(
    expected: Dict[str, Any], actual: Dict[str, Any], expected_name: str, actual_name: str, ignore: Sequence[str] = ()
) -> None:
    """Raise a ``ValueError`` naming the first setting of :meth:`TrialEnv.trial_spec` (outside
    ``ignore``) in which ``actual`` differs from ``expected``, with both values."""
    for key, value in expected.items():
        if key not in ignore and key in actual and actual[key] != value:
            raise ValueError(
                f"{actual_name} does not match {expected_name}: its {key} is {actual[key]!r}, "
                f"{expected_name}'s is {value!r}"
            )


PRIVILEGED_INFO_KEYS = ("problem_id",)


def public_info(info: Dict[str, Any]) -> Dict[str, Any]:
    """``info`` without the privileged keys: what an agent may use at meta-test."""
    return {k: v for k, v in info.items() if k not in PRIVILEGED_INFO_KEYS}
