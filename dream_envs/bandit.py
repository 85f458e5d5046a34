"""MetaBandit-v0: the paper's tabular example (Section 5.2, Appendix C.2)."""

from __future__ import annotations

from typing import Any, Dict, Optional

import cv2
import numpy as np
from gymnasium import spaces

from dream_envs.agents import ScriptedAgent
from dream_envs.checks import check_positive_int
from dream_envs.rendering import COLORS, GridCanvas
from dream_envs.trial_env import EXPLORATION, TrialEnv


class MetaBanditEnv(TrialEnv):
    """A horizon-H bandit whose rewarding action sequence is revealed only by one exploration sequence.

    **Problems.** The |A|^H action sequences; problem ``k`` is the sequence whose step-``t`` action is
    digit ``t`` of ``k`` in base |A| (least significant digit first). All problems are in every split
    (``train``, ``test`` and ``all`` coincide): the example studies exploration, not generalisation.

    **Instruction.** There is a single instruction, encoded ``[1]`` (``[0]`` = none in exploration).

    **Actions.** ``Discrete(n_actions)``, 0-based. There is no end-episode action.

    **Observation** ``obs`` = ``[t, a_0 + 1, ..., a_{H-1} + 1, reveal]`` (MultiDiscrete): the step
    index, the actions taken so far in this episode (0 = not yet) and ``reveal``. In the exploration
    episode, playing action 0 at every one of the H steps (the informative sequence a_*) sets
    ``reveal`` to ``1 + problem_id`` on the last state; any other sequence, and every execution
    episode, leaves it 0.

    **Rewards.** Exploration is reward-free. In execution, playing the problem's own sequence earns
    1 on its last step; everything else earns 0. Every inner episode lasts exactly H steps.

    **Returns.** Optimal trial return (explore with a_*, then play the revealed sequence): 1 per
    execution episode. Without the information: 1 / |A|^H in expectation.

    :param n_actions: |A| (default 8).
    :param horizon: H, the inner-episode horizon (default 1).
    """

    def __init__(
        self,
        n_actions: int = 8,
        horizon: int = 1,
        split: str = "train",
        n_exec_episodes: int = 1,
        reward_free_exploration: bool = True,
        render_mode: Optional[str] = None,
        final_frames: bool = False,
    ) -> None:
        n_actions = check_positive_int("n_actions", n_actions, minimum=2)
        horizon = check_positive_int("horizon", horizon)
        self._n_problems = n_actions**horizon
        if self._n_problems > 2**31:
            raise ValueError(f"n_actions ** horizon = {self._n_problems} problems is too many (at most 2**31)")
        nvec = [horizon + 1] + [n_actions + 1] * horizon + [self._n_problems + 1]
        super().__init__(
            inner_observation_space=spaces.MultiDiscrete(nvec),
            instruction_nvec=[2],
            n_actions=n_actions,
            end_episode_action=None,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=horizon,
            reward_free_exploration=reward_free_exploration,
            render_mode=render_mode,
            final_frames=final_frames,
        )

    @property
    def n_problems(self) -> int:
        return self._n_problems

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return np.arange(self._n_problems)

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        return np.array([[1]])

    def solution(self, problem_id: int) -> list[int]:
        """The problem's rewarding action sequence (digits of the ID in base |A|, least significant first)."""
        return [(problem_id // self.n_actions**t) % self.n_actions for t in range(self.horizon)]

    def _set_problem(self, problem_id: int) -> None:
        self._solution = self.solution(problem_id)

    def _inner_reset(self) -> np.ndarray:
        self._state = np.zeros(self.horizon + 2, dtype=np.int64)
        return self._state.copy()

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        t = int(self._state[0])
        self._state[0] = t + 1
        self._state[1 + t] = action + 1
        actions = self._state[1 : 1 + self.horizon] - 1
        last = t + 1 == self.horizon
        reward = 0.0
        if last and self.phase == EXPLORATION and np.all(actions == 0):
            self._state[-1] = 1 + self.problem_id
        if last and self.instruction is not None and list(actions) == self._solution:
            reward = 1.0
        return self._state.copy(), reward, False

    def _render_frame(self) -> np.ndarray:
        canvas = GridCanvas(max(self.horizon, 1) + 1, 1, cell=64)
        for t in range(self.horizon):
            a = int(self._state[1 + t]) - 1
            canvas.fill(t, 0, COLORS["blue"] if a >= 0 else COLORS["background"])
            canvas.text(t, 0, f"a={a}" if a >= 0 else "-", (255, 255, 255) if a >= 0 else COLORS["text"])
        reveal = int(self._state[-1])
        canvas.fill(self.horizon, 0, COLORS["goal"] if reveal else COLORS["gray"])
        canvas.text(self.horizon, 0, f"id={reveal - 1}" if reveal else "?")
        phase = "explore" if self.phase == EXPLORATION else f"execute {self.episode_index}"
        canvas.caption(f"MetaBandit |A|={self.n_actions} H={self.horizon} ({phase})")
        canvas.caption(f"problem {self.problem_id}: {self._solution}")
        return cv2.resize(canvas.frame(), None, fx=1, fy=1)

    def oracle(self) -> "BanditOracle":
        return BanditOracle(self.n_actions, self.horizon)


class BanditOracle(ScriptedAgent):
    """Optimal scripted agent: plays a_* = (0, ..., 0) in exploration, then the revealed sequence.

    The reveal lands on the exploration episode's last state, which a trial env hands over as
    ``info["final_obs"]`` (the step already returns the execution episode's first observation).
    """

    def __init__(self, n_actions: int, horizon: int) -> None:
        self.n_actions, self.horizon = n_actions, horizon
        self.reset()

    def reset(self) -> None:
        self.known_problem: Optional[int] = None

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        for state in (obs["obs"], info.get("final_obs")):
            if state is not None and int(state[-1]):
                self.known_problem = int(state[-1]) - 1
        if int(obs["phase"]) == EXPLORATION or self.known_problem is None:
            return 0
        t = int(obs["obs"][0])
        return (self.known_problem // self.n_actions**t) % self.n_actions
