"""SignNav3D's world: the rooms, the objects, the sign, the agent's moves and what an execution
episode asks for. Plain numbers and pictures; nothing here needs OpenGL."""

from __future__ import annotations

from typing import Dict, Sequence, Tuple

import cv2
import numpy as np

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

TURN_LEFT, TURN_RIGHT, MOVE_FORWARD, END_EPISODE = 0, 1, 2, 3


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
