"""SignNav3D-v0: the paper's sparse-reward 3D visual navigation (Section 6.2, Appendix B).

The 3D world is drawn by the Miniworld engine (Farama ``miniworld``, OpenGL through ``pyglet``).
The engine is imported lazily, the first time an env is built, so that ``import dream_envs`` works
on machines without OpenGL. On Linux with no ``DISPLAY`` (or with ``PYOPENGL_PLATFORM=egl``) it
renders off-screen through EGL (``pyglet.options["headless"] = True``, which must be set before
pyglet's GL module is first imported); with a ``DISPLAY`` it uses the window system's OpenGL.
Without either, building the env raises :class:`OpenGLUnavailableError` saying what to install.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import heapq
import io
import math
import os
import sys
from types import SimpleNamespace
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
from gymnasium import spaces

from dream_envs.agents import ScriptedAgent
from dream_envs.checks import check_positive_int
from dream_envs.play import play_trials
from dream_envs.trial_env import EXPLORATION, TrialEnv

# ---------------------------------------------------------------------------------------- geometry
# The authors' layout (miniworld's ``Sign(size=10)``): a 10 x 6.5 top room where the agent starts,
# and below it, behind a barrier, a left room (reached through a 6 m wide opening) and a right room
# whose east wall carries the sign. Coordinates are Miniworld's (x, z) floor plane, metres.
ROOM_SIZE = 10.0
BARRIER_GAP = 0.25  # the barrier's thickness: the gap between the top room and the lower rooms
TOP_ROOM_DEPTH = 0.65 * ROOM_SIZE  # the top room spans z in [0, 6.5]
LOWER_ROOMS_Z = (TOP_ROOM_DEPTH + BARRIER_GAP, 1.3 * ROOM_SIZE)  # z range of the left and right rooms
SPLIT_X = 0.6 * ROOM_SIZE  # the left room spans x in [0, 6], the right room x in [6, 10]

FORWARD_STEP = 0.7  # metres per "move forward" (the authors' Sign env)
TURN_DEGREES = 45.0  # degrees per turn (the authors' Sign env)
OBS_SHAPE = (60, 80, 3)  # height, width, RGB: the paper's 80 x 60 x 3 observations

# Problem k: the sign reads SIGN_COLOURS[k]. Instruction [i]: go to an object of type OBJECT_TYPES[i - 1].
SIGN_COLOURS = ("blue", "red")
OBJECT_TYPES = ("ball", "key", "box")
# One object of each (type, colour), at fixed places; only the blue ball is behind the barrier, so
# that the view of the sign from the lower rooms shows no other blue or red thing.
OBJECT_LAYOUT: Dict[Tuple[str, str], Tuple[float, float]] = {
    ("box", "blue"): (1.0, 1.0),
    ("key", "blue"): (5.0, 1.0),
    ("box", "red"): (9.0, 1.0),
    ("ball", "red"): (9.0, 5.0),
    ("key", "red"): (1.0, 5.0),
    ("ball", "blue"): (1.0, 9.0),
}
OBJECT_HEIGHT = 0.6  # balls and keys are drawn this tall (the authors enlarged the key to 0.6 too)
BOX_SIZE = 0.8

# An execution episode's target: the object of the sign's colour and the instruction's type. How it
# ended: touching the target, touching another object, the end-episode action, or the horizon.
EXECUTION_TARGETS: Tuple[Tuple[str, str], ...] = tuple((c, k) for c in SIGN_COLOURS for k in OBJECT_TYPES)
EXECUTION_OUTCOMES = ("right", "wrong", "ended", "timed out")


def execution_target(problem_id: int, instruction: Sequence[int]) -> Tuple[str, str]:
    """The (colour, type) of the object that execution instruction ``instruction`` asks for in problem
    ``problem_id``: the sign's colour, the instruction's type (``[1]`` ball, ``[2]`` key, ``[3]`` box)."""
    return SIGN_COLOURS[int(problem_id)], OBJECT_TYPES[int(instruction[0]) - 1]


# The sign: a white board on the right room's east wall, facing west, at eye height.
SIGN_CENTER = (ROOM_SIZE, 1.5, (LOWER_ROOMS_Z[0] + LOWER_ROOMS_Z[1]) / 2)  # x, y, z
SIGN_SIZE = (2.8, 1.4)  # width, height in metres
SIGN_RGB = {"blue": (0, 0, 255), "red": (255, 0, 0)}  # pure colours, as miniworld's own objects

# Each inner episode starts at a uniformly random pose in this part of the top room (the authors
# sample x in [4, 5], z in [4, 6]); positions from which one step could touch an object are redrawn.
START_REGION = ((3.0, 7.0), (3.3, 6.0))  # (x range, z range)
START_CLEARANCE = FORWARD_STEP + 0.1

# Strongly coloured pixels it takes to read the sign from a view: the scripted reader's threshold,
# and the exploration report's for counting the sign as read.
READ_MIN_PIXELS = 20

HEADLESS_ENV_VAR = "PYOPENGL_PLATFORM"

TURN_LEFT, TURN_RIGHT, MOVE_FORWARD, END_EPISODE = 0, 1, 2, 3


class OpenGLUnavailableError(RuntimeError):
    """SignNav3D-v0 could not initialise OpenGL (no EGL library, no display, no GL context...)."""


def _use_headless() -> bool:
    """Render off-screen through EGL on Linux unless a display is available (or EGL is requested)."""
    if not sys.platform.startswith("linux"):
        return False  # pyglet's headless mode is EGL on Linux only
    return not os.environ.get("DISPLAY") or os.environ.get(HEADLESS_ENV_VAR, "").lower() == "egl"


def _gl_error_message(err: BaseException) -> str:
    mode = "headless EGL (no DISPLAY set)" if _use_headless() else f"the display DISPLAY={os.environ.get('DISPLAY')!r}"
    return (
        f"SignNav3D-v0 needs OpenGL to render its 3D views, but none could be initialised through {mode}: "
        f"{type(err).__name__}: {err}. On a headless Linux machine install Mesa's EGL and OpenGL libraries "
        "and the GLU and FreeType that pyglet loads (e.g. `apt-get install libegl1 libgl1 libegl-mesa0 "
        "libgl1-mesa-dri libglu1-mesa libfreetype6`; with an NVIDIA driver, its EGL serves) and leave DISPLAY unset "
        "(or set PYOPENGL_PLATFORM=egl); "
        "on a desktop, set DISPLAY to a running X server with OpenGL."
    )


def _is_gl_failure(err: BaseException) -> bool:
    # Missing shared libraries surface as ImportError/OSError; failing displays, configs and contexts
    # as pyglet's own exception classes.
    return isinstance(err, (ImportError, OSError)) or type(err).__module__.startswith("pyglet")


_ENGINE: Optional[SimpleNamespace] = None


def _load_engine() -> SimpleNamespace:
    """Import pyglet (headless where needed) and miniworld, and define the world classes on them."""
    import pyglet

    if _use_headless():
        pyglet.options["headless"] = True
    from miniworld.entity import Box, Entity, MeshEnt
    from miniworld.miniworld import MiniWorldEnv
    from miniworld.params import DEFAULT_PARAMS
    from pyglet import gl

    def make_texture(image: np.ndarray) -> int:
        """Upload an RGB uint8 image as a mipmapped GL texture of the current context; return its id."""
        height, width = image.shape[:2]
        data = np.ascontiguousarray(image[::-1])  # GL's rows start at the bottom
        tex_id = gl.GLuint(0)
        gl.glGenTextures(1, tex_id)
        gl.glBindTexture(gl.GL_TEXTURE_2D, tex_id)
        gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
        gl.glTexImage2D(
            gl.GL_TEXTURE_2D,
            0,
            gl.GL_RGB,
            width,
            height,
            0,
            gl.GL_RGB,
            gl.GL_UNSIGNED_BYTE,
            data.ctypes.data_as(ctypes.POINTER(gl.GLubyte)),
        )
        # Mipmaps keep the letters smooth (not aliased) when the sign is small in the 80x60 view.
        gl.glGenerateMipmap(gl.GL_TEXTURE_2D)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_LINEAR)
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
        return int(tex_id.value)

    class SignBoard(Entity):
        """A flat board against a wall at x = ``center[0]``, facing -x, showing one of a few textures."""

        def __init__(self, center: Tuple[float, float, float], size: Tuple[float, float]) -> None:
            super().__init__()
            self.pos = np.array(center, dtype=float)
            self.dir = math.pi  # faces west (-x)
            self.size = size
            self.textures: List[int] = []
            self.shown = 0

        @property
        def is_static(self) -> bool:
            return False  # drawn every frame: its texture changes with the problem

        def render(self) -> None:
            x, y, z = self.pos
            x -= 0.02  # just in front of the wall, to avoid depth fighting
            half_w, half_h = self.size[0] / 2, self.size[1] / 2
            # Unlit (self-luminous), so that white stays white and the letters keep their pure colour.
            gl.glDisable(gl.GL_LIGHTING)
            gl.glEnable(gl.GL_TEXTURE_2D)
            gl.glBindTexture(gl.GL_TEXTURE_2D, self.textures[self.shown])
            gl.glColor3f(1.0, 1.0, 1.0)
            gl.glBegin(gl.GL_QUADS)
            # Counter-clockwise as seen from the west (looking +x, +z is to the viewer's right).
            for u, v in ((0, 0), (1, 0), (1, 1), (0, 1)):
                gl.glTexCoord2f(u, v)
                gl.glVertex3f(x, y - half_h + 2 * half_h * v, z - half_w + 2 * half_w * u)
            gl.glEnd()
            gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
            gl.glEnable(gl.GL_LIGHTING)

    class SignWorld(MiniWorldEnv):
        """The static 3D world: rooms, the six objects and the sign (built once per env)."""

        def __init__(self, view_size: Tuple[int, int]) -> None:
            params = DEFAULT_PARAMS.no_random()
            params.set("forward_step", FORWARD_STEP)
            params.set("turn_step", TURN_DEGREES)
            super().__init__(
                max_episode_steps=10**9,  # the trial env counts steps itself
                obs_width=OBS_SHAPE[1],
                obs_height=OBS_SHAPE[0],
                window_width=view_size[0],
                window_height=view_size[1],
                params=params,
                domain_rand=False,
            )

        def _gen_world(self) -> None:
            lower_min_z, lower_max_z = LOWER_ROOMS_Z
            top = self.add_rect_room(min_x=0, max_x=ROOM_SIZE, min_z=0, max_z=TOP_ROOM_DEPTH)
            left = self.add_rect_room(min_x=0, max_x=SPLIT_X, min_z=lower_min_z, max_z=lower_max_z)
            right = self.add_rect_room(min_x=SPLIT_X, max_x=ROOM_SIZE, min_z=lower_min_z, max_z=lower_max_z)
            self.connect_rooms(top, left, min_x=0, max_x=SPLIT_X)
            self.connect_rooms(left, right, min_z=lower_min_z, max_z=lower_max_z)

            self.objects: List[Tuple[str, str, Any]] = []
            for (kind, colour), (x, z) in OBJECT_LAYOUT.items():
                if kind == "box":
                    ent = Box(color=colour, size=BOX_SIZE)
                else:  # static meshes are compiled once into the scene's display list
                    ent = MeshEnt(mesh_name=f"{kind}_{colour}", height=OBJECT_HEIGHT, static=True)
                self.place_entity(ent, pos=np.array([x, 0.0, z]), dir=0.25 * math.pi)
                self.objects.append((kind, colour, ent))

            self.sign = SignBoard(SIGN_CENTER, SIGN_SIZE)
            self.sign.textures = [make_texture(sign_image(colour)) for colour in SIGN_COLOURS]
            self.entities.append(self.sign)
            self.place_agent(pos=np.array([5.0, 0.0, 5.0]), dir=0.0)

    return SimpleNamespace(pyglet=pyglet, gl=gl, SignWorld=SignWorld)


def _engine() -> SimpleNamespace:
    """The lazily imported engine; a clear error where miniworld or OpenGL is missing."""
    global _ENGINE
    if _ENGINE is None:
        try:
            _ENGINE = _load_engine()
        except ModuleNotFoundError as err:
            if err.name in ("miniworld", "pyglet"):
                raise ImportError(
                    f"SignNav3D-v0 needs the `{err.name}` package: pip install 'miniworld>=2.1' (it brings pyglet)"
                ) from err
            raise OpenGLUnavailableError(_gl_error_message(err)) from err
        except Exception as err:
            if _is_gl_failure(err):
                raise OpenGLUnavailableError(_gl_error_message(err)) from err
            raise
    return _ENGINE


def sign_image(colour: str, width: int = 512, height: int = 256) -> np.ndarray:
    """The sign's face: the colour's name in capitals, in that colour, on a white board."""
    image = np.full((height, width, 3), 255, np.uint8)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), (40, 40, 40), 8)
    text, font, thickness = colour.upper(), cv2.FONT_HERSHEY_DUPLEX, 18
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min(0.85 * width / tw, 0.6 * height / th)  # the same letter height for every word when it fits
    (tw, th), _ = cv2.getTextSize(text, font, scale, thickness)
    origin = ((width - tw) // 2, (height + th) // 2)
    cv2.putText(image, text, origin, font, scale, SIGN_RGB[colour], thickness, cv2.LINE_AA)
    return image


def _dir_vec(direction: float) -> np.ndarray:
    """Miniworld's heading convention: (x, z) of the unit vector the agent faces."""
    return np.array([math.cos(direction), -math.sin(direction)])


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
            reward_bound=1.0,
        )
        engine = _engine()
        # The top-down picture is only drawn for rendering: keep its frame buffer tiny otherwise.
        view_size = (640, 480) if render_mode is not None else (8, 6)
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # miniworld prints its multisampling fallbacks
                self._world = engine.SignWorld(view_size)
        except Exception as err:
            if _is_gl_failure(err):
                raise OpenGLUnavailableError(_gl_error_message(err)) from err
            raise
        world = self._world
        self._touch_distance = [
            ent.radius + world.agent.radius + 1.1 * world.max_forward_step for _, _, ent in world.objects
        ]
        self._planner: Optional[_Planner] = None

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
    def oracle(self) -> "SignNavOracle":
        return SignNavOracle(self)


@dataclasses.dataclass
class SignExplorationReport:
    """What an agent's SignNav3D exploration episodes showed it, one entry per trial: the most pixels
    of the sign's letters in one view (what DREAM's decoder needs to tell the problems apart) and
    whether the agent got past the barrier at all. The sign counts as *read* in a trial whose
    exploration showed at least ``min_pixels`` of them in one view (default :data:`READ_MIN_PIXELS`,
    as many strongly coloured pixels as :func:`sign_colour_from_image` needs). The sign can be read from the top room
    too: from its southern edge, facing east, through the opening to the left room (up to about 160
    letter pixels at (4, 6), which :func:`sign_colour_from_image` reads right), as in the authors'
    layout.

    Counted over the states the agent acted in during exploration; the last state of an exploration
    that the horizon or a touch ended is not among them (it is when the end-episode action ends it).

    Each execution episode is also recorded by its *target* (the object of the sign's colour and the
    instruction's type) and how it ended (:data:`EXECUTION_OUTCOMES`): which objects an execution
    policy reaches, and whether the others time out (it wanders) or are given up (end action).
    """

    sign_pixels: np.ndarray  # [n_trials] the most letter pixels in one exploration view
    past_barrier: np.ndarray  # [n_trials] bool
    exploration_lengths: np.ndarray  # [n_trials]
    execution_returns: np.ndarray  # [n_trials] mean over the trial's execution episodes
    min_pixels: int = READ_MIN_PIXELS
    execution_targets: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))  # [n_episodes]
    execution_outcomes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))  # [n_episodes]

    def outcome_counts(self) -> Dict[Tuple[str, str], Dict[str, int]]:
        """``{(colour, type): {outcome: execution episodes}}`` for every target that was drawn."""
        counts: Dict[Tuple[str, str], Dict[str, int]] = {}
        for target, outcome in zip(self.execution_targets, self.execution_outcomes):
            per_target = counts.setdefault(EXECUTION_TARGETS[target], dict.fromkeys(EXECUTION_OUTCOMES, 0))
            per_target[EXECUTION_OUTCOMES[outcome]] += 1
        return dict(sorted(counts.items(), key=lambda item: EXECUTION_TARGETS.index(item[0])))

    @property
    def sign_seen(self) -> np.ndarray:
        """[n_trials] bool: the exploration showed at least ``min_pixels`` of the sign's letters."""
        return self.sign_pixels >= self.min_pixels

    def summary(self) -> str:
        by_sight = "; ".join(
            f"{label}: {self.execution_returns[mask].mean():.3f} ({int(mask.sum())} trials)"
            for label, mask in (("read", self.sign_seen), ("not read", ~self.sign_seen))
            if mask.any()
        )
        return (
            f"sign read (>= {self.min_pixels} pixels of its letters in a view) in {self.sign_seen.mean():.0%} of "
            f"explorations (any of them in view: {np.mean(self.sign_pixels > 0):.0%}), past the barrier in "
            f"{self.past_barrier.mean():.0%}, exploration length {self.exploration_lengths.mean():.1f}, "
            f"execution return {self.execution_returns.mean():.3f}; execution return with the sign {by_sight}"
            + self.outcomes_summary()
        )

    def outcomes_summary(self) -> str:
        """``; execution by target (right/wrong/ended/timed out): blue ball 0/0/1/13, ...``, or ""."""
        counts = self.outcome_counts()
        if not counts:
            return ""
        per_target = ", ".join(
            f"{colour} {kind} " + "/".join(str(n) for n in per_outcome.values())
            for (colour, kind), per_outcome in counts.items()
        )
        return f"; execution by target ({'/'.join(EXECUTION_OUTCOMES)}): {per_target}"


class _SignViewRecorder(ScriptedAgent):
    """Passes ``agent``'s actions through and notes, in exploration, the most pixels of the sign in one
    view and whether the agent is past the barrier (read from ``env``, which the agent does not see)."""

    def __init__(self, agent: ScriptedAgent, env: SignNav3DEnv) -> None:
        self.agent, self.env = agent, env

    def reset(self) -> None:
        self.agent.reset()
        self.sign_pixels, self.past_barrier = 0, False
        self.execution_targets: List[int] = []  # per execution episode of the trial
        self.last_actions: List[int] = []

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        action = self.agent.act(obs, info)
        if int(obs["phase"]) == EXPLORATION:
            self.sign_pixels = max(self.sign_pixels, self.env.sign_pixels())
            self.past_barrier = self.past_barrier or bool(self.env.agent_position[1] > LOWER_ROOMS_Z[0])
        elif int(obs["episode_start"]):
            target = execution_target(self.env.problem_id, obs["instruction"])
            self.execution_targets.append(EXECUTION_TARGETS.index(target))
            self.last_actions.append(int(action))
        else:
            self.last_actions[-1] = int(action)
        return action

    def execution_outcomes(self, returns: Sequence[float]) -> List[int]:
        """How each of the trial's execution episodes ended, given their returns (a touch gives +-1)."""
        names = [
            "right" if r > 0 else "wrong" if r < 0 else "ended" if last == END_EPISODE else "timed out"
            for r, last in zip(returns, self.last_actions)
        ]
        return [EXECUTION_OUTCOMES.index(name) for name in names]


def exploration_report(
    env: SignNav3DEnv,
    agent: ScriptedAgent,
    n_trials: int = 100,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
    min_pixels: int = READ_MIN_PIXELS,
) -> SignExplorationReport:
    """Play ``n_trials`` trials of ``agent`` (a :class:`~dream_envs.agents.ScriptedAgent`; for a model
    use ``sb3_dream.evaluation.as_trial_agent(model)``) and report what its explorations saw.
    ``problem_ids`` and ``instructions`` pin trials as in :func:`~dream_envs.play.play_trials`."""
    sign_nav = env.unwrapped
    if not isinstance(sign_nav, SignNav3DEnv):
        raise ValueError(f"env must be a SignNav3D-v0 env, got {type(sign_nav).__name__}")
    min_pixels = check_positive_int("min_pixels", min_pixels)
    recorder = _SignViewRecorder(agent, sign_nav)
    rows, targets, outcomes = [], [], []
    for result in play_trials(env, recorder, n_trials, seed, problem_ids, instructions):
        rows.append(
            (recorder.sign_pixels, recorder.past_barrier, result["exploration_length"], np.mean(result["execution_returns"]))
        )
        targets += recorder.execution_targets
        outcomes += recorder.execution_outcomes(result["execution_returns"])
    pixels, past, lengths, returns = (np.array(column) for column in zip(*rows))
    return SignExplorationReport(
        pixels, past.astype(bool), lengths, returns.astype(float), min_pixels, np.array(targets), np.array(outcomes)
    )


class _Planner:
    """Geodesic distance fields over the floor, for the oracle's navigation.

    The floor is a grid of ``cell``-metre cells; a cell is free where the agent (plus a margin) fits
    between the walls and cannot touch an object other than the goal. Distances to the goal cells
    are propagated through free cells with 8-neighbour moves (a vectorised wavefront).
    """

    def __init__(self, env: SignNav3DEnv, cell: float = 0.1, wall_margin: float = 0.1, object_margin: float = 0.15):
        world = env._world
        self.cell = cell
        self.origin = np.array([world.min_x, world.min_z], dtype=float)
        xs = np.arange(world.min_x, world.max_x, cell) + cell / 2
        zs = np.arange(world.min_z, world.max_z, cell) + cell / 2
        gx, gz = np.meshgrid(xs, zs)  # rows: z, columns: x
        self.points = np.stack([gx, gz], axis=-1)
        a = world.wall_segs[:, 0, :][:, [0, 2]]
        ab = world.wall_segs[:, 1, :][:, [0, 2]] - a
        p = self.points.reshape(-1, 1, 2)
        t = np.clip(np.sum((p - a) * ab, -1) / np.sum(ab * ab, -1), 0.0, 1.0)
        wall_dist = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(axis=1).reshape(gx.shape)
        self.walls_free = wall_dist > world.agent.radius + wall_margin
        self.object_zones = [
            np.linalg.norm(self.points - pos, axis=-1) < d + object_margin
            for (_, _, pos), d in zip(env.object_positions(), env._touch_distance)
        ]
        self._fields: Dict[Any, np.ndarray] = {}

    def field(self, key: Any, goal: np.ndarray, target: Optional[int] = None) -> np.ndarray:
        """Distance (metres) to the ``goal`` cells, avoiding every object zone but ``target``'s."""
        if key not in self._fields:
            free = self.walls_free.copy()
            for i, zone in enumerate(self.object_zones):
                if i != target:
                    free &= ~zone
            dist = np.where(goal & free, 0.0, np.inf)
            moves = [(dz, dx, self.cell * math.hypot(dz, dx)) for dz in (-1, 0, 1) for dx in (-1, 0, 1) if dz or dx]
            height, width = dist.shape
            while True:
                new = dist.copy()
                padded = np.pad(dist, 1, constant_values=np.inf)
                for dz, dx, cost in moves:
                    neighbour = padded[slice(1 + dz, 1 + dz + height), slice(1 + dx, 1 + dx + width)]
                    np.minimum(new, neighbour + cost, out=new)
                new[~free] = np.inf
                if np.array_equal(new, dist):
                    break
                dist = new
            self._fields[key] = dist
        return self._fields[key]

    def lookup(self, field: np.ndarray, position: np.ndarray) -> float:
        col, row = ((position - self.origin) // self.cell).astype(int)
        if 0 <= row < field.shape[0] and 0 <= col < field.shape[1]:
            return float(field[row, col])
        return math.inf


def sign_colour_from_image(image: np.ndarray, min_pixels: int = READ_MIN_PIXELS) -> Optional[int]:
    """Read the sign's colour from an RGB view of it: the problem ID (0 blue, 1 red), or None if unsure.

    Counts strongly blue and strongly red pixels (the letters); the sky and walls are neither.
    """
    rgb = image.astype(np.int16)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    n_blue = int(np.count_nonzero(b - np.maximum(r, g) > 100))
    n_red = int(np.count_nonzero(r - np.maximum(g, b) > 100))
    if max(n_blue, n_red) < min_pixels or min(n_blue, n_red) * 4 > max(n_blue, n_red):
        return None
    return 0 if n_blue > n_red else 1


class SignNavOracle(ScriptedAgent):
    """The scripted optimal agent of :class:`SignNav3DEnv` (explorer + executor).

    It is a planner with a map: it holds the env and reads the agent's pose and the (fixed,
    problem-independent) object positions from it to *navigate*. The sign's colour it reads only
    from the observed images (:func:`sign_colour_from_image`), never from the problem ID.

    * Exploration: walk around the barrier to a spot in the lower rooms from which the sign is at
      most ``read_distance`` metres away and seen at most ``max_read_angle`` degrees off its face,
      facing it; read its colour from the view; end the episode (action 3).
    * Execution: walk to the object of the read colour and the instructed type, never touching
      another. If the colour is unknown (the sign was never read), end the episode at once:
      touching nothing earns 0, as much as guessing does in expectation.

    Paths are short action sequences found by A* over the agent's exact poses (the dynamics are
    deterministic), guided by a geodesic distance field over the floor; the plan is replayed, and
    made again whenever the pose is not the one it expects. With the default geometry and horizon it
    reads the sign in at most 15 steps and scores 1 in every trial we measured.
    """

    def __init__(
        self,
        env: SignNav3DEnv,
        read_distance: float = 4.5,
        max_read_angle: float = 50.0,
        max_expansions: int = 50_000,
    ) -> None:
        self.env = env
        if env._planner is None:
            env._planner = _Planner(env)
        self.planner = env._planner
        self.max_expansions = max_expansions
        self.sign_xz = np.array([SIGN_CENTER[0], SIGN_CENTER[2]])
        offset = self.planner.points - self.sign_xz
        distance = np.linalg.norm(offset, axis=-1)
        self.reading_cells = (
            (self.planner.points[..., 1] > LOWER_ROOMS_Z[0] + 0.5)  # past the barrier
            & (distance <= read_distance)
            & (np.abs(np.arctan2(offset[..., 1], -offset[..., 0])) <= math.radians(max_read_angle))
        )
        self.close_reading_cells = self.reading_cells & (distance <= 3.0)
        self.reset()

    def reset(self) -> None:
        self.colour: Optional[int] = None  # the problem ID, as read from the sign
        self._plan: List[int] = []
        self._expected: Optional[Tuple[np.ndarray, float]] = None
        self._goal: Any = None

    # ------------------------------------------------------------------ decisions
    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        env = self.env
        if int(obs["episode_start"]):
            self._plan, self._goal = [], None
        if int(obs["phase"]) == EXPLORATION:
            if self.colour is not None:
                return END_EPISODE
            cells = self.reading_cells if self._goal != "close" else self.close_reading_cells
            if self._reads_from(env.agent_position, env.agent_direction, cells):
                self.colour = sign_colour_from_image(obs["obs"])
                if self.colour is not None:
                    return END_EPISODE
                if self._goal == "close":  # unreadable even up close (never seen): give up exploring
                    return END_EPISODE
                self._goal, self._plan = "close", []  # unreadable from here: go nearer
                cells = self.close_reading_cells
            self._goal = self._goal or "sign"
            return self._follow(
                self.planner.field(self._goal, cells),
                is_goal=lambda pos, heading, touched: self._reads_from(pos, heading, cells),
                target=None,
            )

        if self.colour is None or int(obs["instruction"][0]) == 0:
            return END_EPISODE
        kind = OBJECT_TYPES[int(obs["instruction"][0]) - 1]
        objects = env.object_positions()
        target = next(i for i, (k, c, _) in enumerate(objects) if k == kind and c == SIGN_COLOURS[self.colour])
        goal_cells = np.linalg.norm(self.planner.points - objects[target][2], axis=-1) < env._touch_distance[target]
        return self._follow(
            self.planner.field(("object", target), goal_cells, target),
            is_goal=lambda pos, heading, touched: touched == target,
            target=target,
        )

    def _reads_from(self, position: np.ndarray, heading: float, cells: np.ndarray) -> bool:
        """Whether ``position`` is a reading spot (in ``cells``) and ``heading`` faces the sign."""
        if self.planner.lookup(cells, position) != 1.0:
            return False
        d = self.sign_xz - position
        error = (math.atan2(-d[1], d[0]) - heading + math.pi) % (2 * math.pi) - math.pi
        return abs(error) <= math.radians(TURN_DEGREES / 2) + 1e-6

    # ------------------------------------------------------------------ planning
    def _follow(
        self,
        field: np.ndarray,
        is_goal: Callable[[np.ndarray, float, Optional[int]], bool],
        target: Optional[int],
    ) -> int:
        env = self.env
        position, heading = env.agent_position, env.agent_direction
        on_track = (
            self._plan
            and self._expected is not None
            and np.allclose(self._expected[0], position, atol=1e-6)
            and abs(self._expected[1] - heading) < 1e-6
        )
        if not on_track:
            self._plan = self._search(position, heading, field, is_goal, target) or []
        if not self._plan:
            return END_EPISODE  # no way to the goal within the search budget (never with the defaults)
        action = self._plan.pop(0)
        self._expected = self._transition(position, heading, action)
        return action

    @staticmethod
    def _transition(position: np.ndarray, heading: float, action: int) -> Tuple[np.ndarray, float]:
        turn = math.radians(TURN_DEGREES)
        if action == TURN_LEFT:
            return position, heading + turn
        if action == TURN_RIGHT:
            return position, heading - turn
        return position + FORWARD_STEP * _dir_vec(heading), heading

    def _search(
        self,
        position: np.ndarray,
        heading: float,
        field: np.ndarray,
        is_goal: Callable[[np.ndarray, float, Optional[int]], bool],
        target: Optional[int],
    ) -> Optional[List[int]]:
        """A* over exact poses: a (near-)shortest action sequence reaching ``is_goal``, or None."""
        env = self.env

        def h(pos: np.ndarray) -> float:
            d = self.planner.lookup(field, pos)
            return d / FORWARD_STEP if math.isfinite(d) else 1e3

        # A pose's heading is the start's plus a multiple of the turn: keep that multiple (mod 8).
        n_headings = int(round(360 / TURN_DEGREES))
        if is_goal(position, heading, None):
            return []
        frontier: List[Tuple[float, int, int]] = [(h(position), 0, 0)]
        nodes = [(position, 0, -1, -1)]  # (position, heading index, parent node, action)
        seen = {(round(position[0] / 0.05), round(position[1] / 0.05), 0)}

        expansions = 0
        while frontier and expansions < self.max_expansions:
            _, g, node = heapq.heappop(frontier)
            expansions += 1
            pos, k, _, _ = nodes[node]
            for action in (MOVE_FORWARD, TURN_LEFT, TURN_RIGHT):
                new_pos, _ = self._transition(pos, heading + math.radians(TURN_DEGREES) * k, action)
                new_k = k + (action == TURN_LEFT) - (action == TURN_RIGHT)
                touched = None
                if action == MOVE_FORWARD:
                    if env._blocked(new_pos):
                        continue  # a wasted step
                    touched = env._touched(new_pos)
                    if touched is not None and touched != target:
                        continue
                key = (round(new_pos[0] / 0.05), round(new_pos[1] / 0.05), new_k % n_headings)
                if key in seen:
                    continue
                seen.add(key)
                nodes.append((new_pos, new_k, node, action))
                if is_goal(new_pos, heading + math.radians(TURN_DEGREES) * new_k, touched):
                    plan, i = [], len(nodes) - 1
                    while nodes[i][2] >= 0:
                        plan.append(nodes[i][3])
                        i = nodes[i][2]
                    return plan[::-1]
                if touched is None:
                    heapq.heappush(frontier, (g + 1 + h(new_pos), g + 1, len(nodes) - 1))
        return None
