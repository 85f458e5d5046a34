"""SignNav3D's scripted optimal agent: it reads the sign from its views and navigates with a planner."""

from __future__ import annotations

import heapq
import math
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from dream_envs.agents import ScriptedAgent
from dream_envs.sign_nav.layout import (
    END_EPISODE,
    FORWARD_STEP,
    LOWER_ROOMS_Z,
    MOVE_FORWARD,
    OBJECT_TYPES,
    READ_MIN_PIXELS,
    SIGN_CENTER,
    SIGN_COLOURS,
    TURN_DEGREES,
    TURN_LEFT,
    TURN_RIGHT,
)
from dream_envs.trial_env import EXPLORATION

if TYPE_CHECKING:
    from dream_envs.sign_nav.env import SignNav3DEnv


def _dir_vec(direction: float) -> np.ndarray:
    """Miniworld's heading convention: (x, z) of the unit vector the agent faces."""
    return np.array([math.cos(direction), -math.sin(direction)])


class Planner:
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
    made again whenever the pose is not the one it expects.
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
            env._planner = Planner(env)
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
