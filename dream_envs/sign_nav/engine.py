"""The Miniworld engine behind SignNav3D-v0, and whether OpenGL is available to draw it.

The 3D world is drawn by the Miniworld engine (Farama ``miniworld``, OpenGL through ``pyglet``).
The engine is imported lazily, the first time an env is built, so that ``import dream_envs`` works
on machines without OpenGL. On Linux with no ``DISPLAY`` (or with ``PYOPENGL_PLATFORM=egl``) it
renders off-screen through EGL (``pyglet.options["headless"] = True``, which must be set before
pyglet's GL module is first imported); with a ``DISPLAY`` it uses the window system's OpenGL.
Without either, building the env raises :class:`OpenGLUnavailableError` saying what to install;
:func:`opengl_available` asks the same question without building one.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import math
import os
import sys
from types import SimpleNamespace
from typing import Any, Iterator, List, Optional, Tuple

import numpy as np

from dream_envs.sign_nav.layout import (
    BOX_SIZE,
    FORWARD_STEP,
    LOWER_ROOMS_Z,
    OBJECT_HEIGHT,
    OBJECT_LAYOUT,
    OBS_SHAPE,
    ROOM_SIZE,
    SIGN_CENTER,
    SIGN_COLOURS,
    SIGN_SIZE,
    SPLIT_X,
    TOP_ROOM_DEPTH,
    TURN_DEGREES,
    sign_image,
)

HEADLESS_ENV_VAR = "PYOPENGL_PLATFORM"


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


@contextlib.contextmanager
def _gl_errors() -> Iterator[None]:
    """Turn an OpenGL failure raised inside the block into an :class:`OpenGLUnavailableError`."""
    try:
        yield
    except Exception as err:
        if _is_gl_failure(err):
            raise OpenGLUnavailableError(_gl_error_message(err)) from err
        raise


_ENGINE: Optional[SimpleNamespace] = None


def _import_engine() -> SimpleNamespace:
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


def load_engine() -> SimpleNamespace:
    """The engine (``pyglet``, ``gl`` and the ``SignWorld`` class), imported on the first call.

    :raises ImportError: where ``miniworld`` or ``pyglet`` is not installed.
    :raises OpenGLUnavailableError: where their OpenGL libraries cannot be loaded.
    """
    global _ENGINE
    if _ENGINE is None:
        try:
            with _gl_errors():
                _ENGINE = _import_engine()
        except OpenGLUnavailableError as err:
            missing = err.__cause__
            if isinstance(missing, ModuleNotFoundError) and missing.name in ("miniworld", "pyglet"):
                raise ImportError(
                    f"SignNav3D-v0 needs the `{missing.name}` package: pip install 'miniworld>=2.1' (it brings pyglet)"
                ) from missing
            raise
    return _ENGINE


def make_world(view_size: Tuple[int, int]) -> Any:
    """A new ``SignWorld`` with its own GL context; ``view_size`` is its top-down picture's (width, height).

    :raises OpenGLUnavailableError: where no GL context can be made.
    """
    engine = load_engine()
    with _gl_errors(), contextlib.redirect_stdout(io.StringIO()):  # miniworld prints its multisampling fallbacks
        return engine.SignWorld(view_size)


def opengl_available() -> Tuple[bool, str]:
    """Whether SignNav3D-v0 can be built here: ``(True, "")``, or ``(False, reason)`` where the engine
    or an OpenGL context is missing, the reason saying what to install. Makes (and frees) a 1x1 hidden
    GL context, as every env does."""
    try:
        pyglet = load_engine().pyglet
        with _gl_errors():
            pyglet.window.Window(width=1, height=1, visible=False).close()
    except (ImportError, OpenGLUnavailableError) as err:
        return False, str(err)
    return True, ""
