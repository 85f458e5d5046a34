"""SignNav3D-v0: the paper's sparse-reward 3D visual navigation (Section 6.2, Appendix B), as a trial env."""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Tuple

import cv2
import numpy as np
from gymnasium import spaces

from dream_envs.sign_nav.engine import make_world
from dream_envs.sign_nav.layout import (
    END_EPISODE,
    FORWARD_STEP,
    MOVE_FORWARD,
    OBJECT_TYPES,
    OBS_SHAPE,
    SIGN_CENTER,
    SIGN_COLOURS,
    SIGN_RGB,
    SIGN_SIZE,
    START_CLEARANCE,
    START_REGION,
    TURN_DEGREES,
    TURN_LEFT,
)
from dream_envs.sign_nav.oracle import Planner, SignNavOracle
from dream_envs.trial_env import EXPLORATION, TrialEnv


class SignNav3DEnv(TrialEnv):
    """Sparse-reward 3D visual navigation: read a sign behind a barrier, then go to the right object.

    Built on the Miniworld engine (the authors' ``MiniWorld-Sign-v0`` layout, ``size=10``): the agent
    starts each inner episode at a random pose in the top room, on the far side of a barrier from a
    sign on the east wall of the right-hand lower room. The sign reads BLUE or RED (the *problem*),
    in big letters of that colour on a white board. A ball, a key and a box of each of the two
    colours stand at fixed places. Touching an object (coming within Miniworld's ``near`` distance
    of it) ends the inner episode.

    **Problems.** 2: ``0`` = the sign says blue, ``1`` = red. There is nothing to hold out: the
    ``train``, ``test`` and ``all`` splits are all both problems (the paper evaluates on them).

    **Instruction.** Which type of object to go to: ``[1]`` ball, ``[2]`` key, ``[3]`` box
    (``instruction_nvec = [4]``; ``[0]`` = none, in reward-free exploration). The paper's
    i = 0, 1, 2 are our 1, 2, 3. Drawn uniformly for each execution episode.

    **Observation** ``obs``: ``Box(0, 255, (60, 80, 3), uint8)``, the agent's egocentric RGB view.
    The sign's colour is visible only in it (and only when the sign is in view).

    **Actions.** ``Discrete(4)``: 0 turn left 45 degrees, 1 turn right 45 degrees, 2 move forward
    0.7 m (blocked by walls and objects), 3 end the inner episode (``end_episode_action = 3``).

    **Rewards.** Touching the object whose colour is the sign's and whose type is the instruction's:
    +1; touching any other object: -1; everything else (the end-episode action included): 0. In
    reward-free exploration (no instruction) touching an object still ends the episode, with 0.

    **Termination.** An inner episode ends when an object is touched, on the end-episode action, or
    after ``horizon`` steps (default 20, as the authors' ``max_episode_steps=20``); the trial ends
    after the last execution episode.

    **Returns.** Optimal execution return: 1 (read the sign during exploration, then go to the
    instructed object of its colour). Without reading the sign, guessing the colour earns 0 in
    expectation, and so does touching nothing.

    **Rendering** (``render_mode="rgb_array"``): the agent's 80x60 view enlarged 8 times (what the
    agent sees) beside Miniworld's top-down map (the agent is the red triangle, the sign the coloured
    bar on the right-hand wall), with a caption.

    :param split: "train", "test" or "all" (the same two problems).
    :param n_exec_episodes: execution episodes per trial.
    :param horizon: inner-episode horizon (steps).
    :param reward_free_exploration: see :class:`~dream_envs.trial_env.TrialEnv`.
    :param render_mode: ``None`` or ``"rgb_array"``.
    :param final_frames: see :class:`~dream_envs.trial_env.TrialEnv` (pictures of each inner episode's
        last state in ``info``).
    :raises OpenGLUnavailableError: (a ``RuntimeError``) where OpenGL cannot be initialised.
    """

    metadata: Dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 4}
    action_names = ("left", "right", "forward", "end")

    def __init__(
        self,
        split: str = "train",
        n_exec_episodes: int = 1,
        horizon: int = 20,
        reward_free_exploration: bool = True,
        render_mode: Optional[str] = None,
        final_frames: bool = False,
    ) -> None:
        super().__init__(
            inner_observation_space=spaces.Box(0, 255, shape=OBS_SHAPE, dtype=np.uint8),
            instruction_nvec=[len(OBJECT_TYPES) + 1],
            n_actions=4,
            end_episode_action=END_EPISODE,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=horizon,
            reward_free_exploration=reward_free_exploration,
            render_mode=render_mode,
            final_frames=final_frames,
            reward_bound=1.0,
        )
        # The top-down picture is only drawn for rendering: keep its frame buffer tiny otherwise.
        self._world = make_world((640, 480) if render_mode is not None else (8, 6))
        world = self._world
        self._touch_distance = [
            ent.radius + world.agent.radius + 1.1 * world.max_forward_step for _, _, ent in world.objects
        ]
        self._planner: Optional[Planner] = None  # built by the first oracle

    # ------------------------------------------------------------------ the problem family
    @property
    def n_problems(self) -> int:
        return len(SIGN_COLOURS)

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return np.arange(len(SIGN_COLOURS))  # nothing held out: every split is both problems

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        return np.arange(1, len(OBJECT_TYPES) + 1).reshape(-1, 1)

    def _set_problem(self, problem_id: int) -> None:
        self._world.sign.shown = problem_id

    def _inner_reset(self) -> np.ndarray:
        (x_lo, x_hi), (z_lo, z_hi) = START_REGION
        while True:  # rejection sampling; most draws are accepted
            x, z = self.np_random.uniform(x_lo, x_hi), self.np_random.uniform(z_lo, z_hi)
            if self._clearance(np.array([x, z])) > START_CLEARANCE:
                break
        self._set_agent_pose(x, z, float(self.np_random.uniform(-math.pi, math.pi)))
        return self._world.render_obs()

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        world = self._world
        if action == MOVE_FORWARD:
            world.move_agent(FORWARD_STEP, 0.0)  # stays put if blocked
        else:
            world.turn_agent(TURN_DEGREES if action == TURN_LEFT else -TURN_DEGREES)
        obs = world.render_obs()
        touched = self._touched(self.agent_position)
        if touched is None:
            return obs, 0.0, False
        if self.instruction is None:
            return obs, 0.0, True  # reward-free exploration: touching still ends the episode
        kind, colour, _ = world.objects[touched]
        right = colour == SIGN_COLOURS[self.problem_id] and kind == OBJECT_TYPES[int(self.instruction[0]) - 1]
        return obs, (1.0 if right else -1.0), True

    # ------------------------------------------------------------------ geometry helpers
    @property
    def agent_position(self) -> np.ndarray:
        """The agent's (x, z) position on the floor, metres."""
        return np.array(self._world.agent.pos[[0, 2]], dtype=float)

    @property
    def agent_direction(self) -> float:
        """The agent's heading, radians (Miniworld's convention: 0 faces +x, turning left adds)."""
        return float(self._world.agent.dir)

    def sign_pixels(self) -> int:
        """How many pixels of the agent's current view show the sign's letters: those that differ
        between the view with the blue sign and the view with the red one (both rendered, then the
        problem's restored). 0 when the sign is out of view. For reports and tests; the agent never
        calls it."""
        sign = self._world.sign
        shown = sign.shown
        try:
            views = []
            for k in range(len(SIGN_COLOURS)):
                sign.shown = k
                views.append(self._world.render_obs())
        finally:
            sign.shown = shown
        return int(np.count_nonzero(np.any(views[0] != views[1], axis=-1)))

    def object_positions(self) -> List[Tuple[str, str, np.ndarray]]:
        """``(type, colour, (x, z))`` of the six objects (a fixed map, the same in every problem)."""
        return [(kind, colour, np.array(ent.pos[[0, 2]], dtype=float)) for kind, colour, ent in self._world.objects]

    def _clearance(self, position: np.ndarray) -> float:
        """How far ``position`` is from touching the nearest object (negative: touching)."""
        return min(
            float(np.linalg.norm(position - ent.pos[[0, 2]])) - d
            for (_, _, ent), d in zip(self._world.objects, self._touch_distance)
        )

    def _touched(self, position: np.ndarray) -> Optional[int]:
        """Index of the object an agent at ``position`` touches, if any."""
        for i, ((_, _, ent), d) in enumerate(zip(self._world.objects, self._touch_distance)):
            if np.linalg.norm(position - ent.pos[[0, 2]]) < d:
                return i
        return None

    def _blocked(self, position: np.ndarray) -> bool:
        """Whether the agent cannot stand at ``position`` (a wall or an object is in the way)."""
        world = self._world
        return bool(world.intersect(world.agent, np.array([position[0], 0.0, position[1]]), world.agent.radius))

    def _set_agent_pose(self, x: float, z: float, direction: float) -> None:
        """Teleport the agent (for the episode start, and for tests); does not render."""
        self._world.agent.pos = np.array([x, 0.0, z], dtype=float)
        self._world.agent.dir = float(direction)

    # ------------------------------------------------------------------ rendering
    def _render_frame(self) -> np.ndarray:
        world = self._world
        scale_up = 8
        view = cv2.resize(
            self._inner_obs, (OBS_SHAPE[1] * scale_up, OBS_SHAPE[0] * scale_up), interpolation=cv2.INTER_NEAREST
        )
        top, scale = world.render_top_view(world.vis_fb, return_scale=True)
        top = np.ascontiguousarray(top)

        # The sign is a vertical board, invisible from above: draw it as a bar of its colour.
        def to_px(x: float, z: float) -> Tuple[int, int]:
            return int(x * scale["x_scale"] + scale["x_offset"]), int(z * scale["z_scale"] + scale["z_offset"])

        colour = SIGN_COLOURS[self.problem_id]
        cx, _, cz = SIGN_CENTER
        cv2.line(
            top, to_px(cx - 0.1, cz - SIGN_SIZE[0] / 2), to_px(cx - 0.1, cz + SIGN_SIZE[0] / 2), SIGN_RGB[colour], 6
        )
        top = cv2.resize(top, (view.shape[0] * top.shape[1] // top.shape[0], view.shape[0]))
        frame = np.concatenate([view, top], axis=1)

        caption = np.full((48, frame.shape[1], 3), 245, np.uint8)
        phase = "exploration" if self.phase == EXPLORATION else f"execution {self.episode_index}"
        goal = (
            "no instruction" if self.instruction is None else f"go to the {OBJECT_TYPES[int(self.instruction[0]) - 1]}"
        )
        lines = [
            f"SignNav3D  problem {self.problem_id}: the sign says {colour.upper()}",
            f"{phase}: {goal}   step {self._t}/{self.horizon}",
        ]
        for row, text in enumerate(lines):
            cv2.putText(caption, text, (8, 19 + 22 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (30, 30, 30), 1, cv2.LINE_AA)
        return np.concatenate([frame, caption], axis=0)

    def close(self) -> None:
        world = getattr(self, "_world", None)
        if world is not None:
            world.shadow_window.close()  # frees this env's GL context and frame buffers
            self._world = None
        super().close()

    # ------------------------------------------------------------------ oracle
    def oracle(self) -> SignNavOracle:
        return SignNavOracle(self)
