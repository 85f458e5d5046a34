"""Write your own meta-RL env with the trial API, then train DREAM on it.

    python examples/custom_trial_env.py --steps 20000

:class:`SignCorridorEnv` below is a complete instruction-based meta-RL (IMRL) problem family in
about 80 lines: a :class:`dream_envs.TrialEnv` subclass defines only

* the problems and their splits (``n_problems``, ``_split_problem_ids``),
* the instructions (``_instruction_choices``, drawn uniformly),
* the inner MDP of a problem (``_set_problem``, ``_inner_reset``, ``_inner_step``) and a picture
  (``_render_frame``),

and the base class turns it into Gymnasium episodes that are whole trials (a reward-free
exploration episode, then execution episodes), with the Dict observation
(``obs, instruction, phase, episode_start, prev_action, prev_reward``), the privileged
``info["problem_id"]``, ``reset(options={"problem_id": ...})`` and argument checks. An ``oracle()``
(the optimal scripted agent) is optional but lets you check the env and know the best return.

The script checks the env with Gymnasium's env checker, scores the oracle and a random agent,
trains DREAM and meta-tests it.
"""

from __future__ import annotations

import argparse
from typing import Any, Dict, Optional

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env

from dream_envs import EXPLORATION, RandomAgent, ScriptedAgent, TrialEnv
from dream_envs.rendering import COLORS, GridCanvas
from sb3_dream import DREAM, evaluate_meta

LEFT, RIGHT, STOP = 0, 1, 2  # then one "answer c" action per code c


class SignCorridorEnv(TrialEnv):
    """A corridor whose far end shows a secret code; execution pays for answering it.

    **Problems.** ``n_codes`` problems: problem ``k``'s code is ``k``. Every split holds all of them
    (like MetaBandit-v0: a code never seen in training could not be answered).

    **Instruction.** One instruction, ``[1]``: "answer the code" (``[0]`` = none while exploring).

    **Actions.** ``Discrete(3 + n_codes)``: 0 left, 1 right, 2 stop (ends the inner episode: the
    end-episode action), ``3 + c`` answer code ``c`` (ends an execution episode; a no-op while
    exploring).

    **Observation** ``obs`` = ``[x, sign]`` (MultiDiscrete): the agent's cell ``0 .. length - 1``
    (every inner episode starts at 0) and ``1 + code`` when standing at the far end, else 0.

    **Rewards.** Exploration is reward-free. In execution: -0.1 per move, +1 for the right answer,
    0 for a wrong one. Optimal: read the code while exploring, then answer at once (return 1.0);
    an agent that did not explore walks to the sign first (return 1 - 0.1 (length - 1) = 0.7).

    :param length: corridor cells (the sign is ``length - 1`` steps away).
    :param n_codes: number of codes (problems).
    """

    def __init__(
        self,
        length: int = 4,
        n_codes: int = 4,
        split: str = "train",
        n_exec_episodes: int = 1,
        horizon: int = 6,
        reward_free_exploration: bool = True,
        render_mode: Optional[str] = None,
    ) -> None:
        if length < 2 or n_codes < 2:
            raise ValueError(f"length and n_codes must be >= 2, got length={length}, n_codes={n_codes}")
        self.length, self.n_codes = length, n_codes
        super().__init__(
            inner_observation_space=spaces.MultiDiscrete([length, n_codes + 1]),
            instruction_nvec=[2],
            n_actions=3 + n_codes,
            end_episode_action=STOP,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=horizon,
            reward_free_exploration=reward_free_exploration,
            render_mode=render_mode,
        )

    @property
    def n_problems(self) -> int:
        return self.n_codes

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return np.arange(self.n_codes)

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        return np.array([[1]])  # one instruction ("say the code"), drawn uniformly like any list

    def _set_problem(self, problem_id: int) -> None:
        self._code = problem_id

    def _state(self) -> np.ndarray:
        sign = 1 + self._code if self._x == self.length - 1 else 0
        return np.array([self._x, sign], dtype=np.int64)

    def _inner_reset(self) -> np.ndarray:
        self._x = 0
        return self._state()

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        if action in (LEFT, RIGHT):
            self._x = int(np.clip(self._x + (1 if action == RIGHT else -1), 0, self.length - 1))
            return self._state(), -0.1, False
        if self.instruction is None:  # answering means nothing while exploring reward-free
            return self._state(), 0.0, False
        return self._state(), float(action - 3 == self._code), True

    def _render_frame(self) -> np.ndarray:
        canvas = GridCanvas(self.length, 1, cell=64)
        canvas.fill(self.length - 1, 0, COLORS["goal"])
        canvas.text(self.length - 1, 0, f"code {self._code}")
        canvas.agent(self._x, 0)
        phase = "exploration" if self.phase == EXPLORATION else f"execution {self.episode_index}"
        canvas.caption(f"SignCorridor, problem {self.problem_id}: {phase}, step {self._t}/{self.horizon}")
        return canvas.frame()

    def oracle(self) -> "SignCorridorOracle":
        return SignCorridorOracle()


class SignCorridorOracle(ScriptedAgent):
    """Explores to the sign and stops; then answers at once (or walks to the sign if it has not seen it)."""

    def reset(self) -> None:
        self.code: Optional[int] = None

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        for state in (obs["obs"], info.get("final_obs")):  # final_obs: the exploration's last state
            if state is not None and int(state[1]):
                self.code = int(state[1]) - 1
        if int(obs["phase"]) == EXPLORATION:
            return STOP if self.code is not None else RIGHT
        return 3 + self.code if self.code is not None else RIGHT


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20_000, help="env steps of DREAM training")
    parser.add_argument("--n-envs", type=int, default=4)
    parser.add_argument("--eval-trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)

    # 1. The env obeys the Gymnasium API (spaces, seeding, reset/step signatures).
    check_env(SignCorridorEnv(), skip_render_check=True)

    # 2. Baselines: the oracle's return is the best possible; a random agent's is the floor.
    env = SignCorridorEnv(split="test")
    for name, agent in [("oracle", env.oracle()), ("random", RandomAgent(env.action_space, seed=args.seed))]:
        print(f"{name:>7}: {evaluate_meta(agent, env, n_trials=args.eval_trials).summary()}")

    # 3. DREAM on it. Registering an ID is optional: any env constructor works with make_vec_env.
    gym.register("SignCorridor-v0", entry_point=SignCorridorEnv)
    vec_env = make_vec_env("SignCorridor-v0", n_envs=args.n_envs, seed=args.seed)
    # A tiny problem family: start learning after 50 trials and decay epsilon over 5000 steps of
    # each policy (the paper's schedules are for far larger families: see sb3_dream.presets).
    model = DREAM(
        vec_env,
        seed=args.seed,
        exploration_learning_starts=50,
        execution_learning_starts=50,
        eps_decay_steps=5_000,
        target_update_interval=500,
        buffer_size=2_000,
        execution_buffer_size=20_000,
    )
    model.learn(total_timesteps=args.steps)
    print(f"  DREAM: {evaluate_meta(model, 'SignCorridor-v0', n_trials=args.eval_trials).summary()}")


if __name__ == "__main__":
    main()
