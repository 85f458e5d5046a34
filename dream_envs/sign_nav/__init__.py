"""SignNav3D-v0: the paper's sparse-reward 3D visual navigation (Section 6.2, Appendix B).

* :mod:`~dream_envs.sign_nav.layout`: the world's geometry, the sign's face and the actions;
* :mod:`~dream_envs.sign_nav.engine`: the Miniworld/OpenGL engine that draws it, imported only when
  an env is built, and :func:`opengl_available`;
* :mod:`~dream_envs.sign_nav.env`: :class:`SignNav3DEnv`, the trial env;
* :mod:`~dream_envs.sign_nav.oracle`: :class:`SignNavOracle`, the scripted sign reader and planner;
* :mod:`~dream_envs.sign_nav.report`: :func:`exploration_report`.
"""

from dream_envs.sign_nav.engine import OpenGLUnavailableError, opengl_available
from dream_envs.sign_nav.env import SignNav3DEnv
from dream_envs.sign_nav.layout import (
    BARRIER_GAP,
    BOX_SIZE,
    END_EPISODE,
    EXECUTION_OUTCOMES,
    EXECUTION_TARGETS,
    FORWARD_STEP,
    LOWER_ROOMS_Z,
    MOVE_FORWARD,
    OBJECT_HEIGHT,
    OBJECT_LAYOUT,
    OBJECT_TYPES,
    OBS_SHAPE,
    READ_MIN_PIXELS,
    ROOM_SIZE,
    SIGN_CENTER,
    SIGN_COLOURS,
    SIGN_RGB,
    SIGN_SIZE,
    SPLIT_X,
    START_CLEARANCE,
    START_REGION,
    TOP_ROOM_DEPTH,
    TURN_DEGREES,
    TURN_LEFT,
    TURN_RIGHT,
    execution_target,
    sign_image,
)
from dream_envs.sign_nav.oracle import SignNavOracle, sign_colour_from_image
from dream_envs.sign_nav.report import SignExplorationReport, exploration_report

__all__ = [
    "BARRIER_GAP",
    "BOX_SIZE",
    "END_EPISODE",
    "EXECUTION_OUTCOMES",
    "EXECUTION_TARGETS",
    "FORWARD_STEP",
    "LOWER_ROOMS_Z",
    "MOVE_FORWARD",
    "OBJECT_HEIGHT",
    "OBJECT_LAYOUT",
    "OBJECT_TYPES",
    "OBS_SHAPE",
    "READ_MIN_PIXELS",
    "ROOM_SIZE",
    "SIGN_CENTER",
    "SIGN_COLOURS",
    "SIGN_RGB",
    "SIGN_SIZE",
    "SPLIT_X",
    "START_CLEARANCE",
    "START_REGION",
    "TOP_ROOM_DEPTH",
    "TURN_DEGREES",
    "TURN_LEFT",
    "TURN_RIGHT",
    "OpenGLUnavailableError",
    "SignExplorationReport",
    "SignNav3DEnv",
    "SignNavOracle",
    "execution_target",
    "exploration_report",
    "opengl_available",
    "sign_colour_from_image",
    "sign_image",
]
