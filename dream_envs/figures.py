"""Pictures of what an agent explores: exploration episodes drawn on the grid (the paper's Figures 7, 8).

:func:`exploration_paths` plays trials of any trial agent (a :class:`~dream_envs.agents.ScriptedAgent`;
for a model ``sb3_dream.evaluation.as_trial_agent(model)``) in a grid family (MetaBus-v0, MetaCook-v0)
and keeps each exploration episode as an :class:`ExplorationPath`: the cells it went through, its
actions and what it found (a bus ridden, the map read, a fridge opened), the latter resolved with
the trial's problem, which the agent never sees. :func:`draw_explorations` draws the grid once and
the paths of several trials over it, each shifted by a small offset so that paths along the same
cells stay apart; :func:`exploration_figure` puts one such panel per agent side by side and
:func:`path_rows` gives the plotted points as table rows (a CSV makes the drawing reproducible).

matplotlib is imported only by the drawing functions (it is an optional dependency of the package).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import gymnasium as gym
import numpy as np

from dream_envs.agents import ScriptedAgent
from dream_envs.bus import (
    ACTION_NAMES,
    BUS,
    COLORED_DESTINATIONS,
    COLORED_STOPS,
    GOALS,
    GRAY_DESTINATIONS,
    GRAY_STOPS,
    MAP_CELL,
    RIDE,
    SIZE,
    MetaBusEnv,
    bus_stop_of,
    shows_map,
)
from dream_envs.cook.env import MetaCookEnv
from dream_envs.cook.kitchen import FRIDGE_POS, GRID_SIZE, POT_POS, fridge_contents, fridge_picked
from dream_envs.play import play_trials
from dream_envs.rendering import COLORS, PALETTE
from dream_envs.report import TrialRecorder
from dream_envs.trial_env import EXPLORATION, TrialEnv

Cell = Tuple[int, int]
FAMILIES = ("MetaBus-v0", "MetaCook-v0")
EVENT_KINDS = ("ride", "map", "fridge")
PATH_COLUMNS = (
    "panel", "trial", "problem_id", "step", "x", "y", "plot_x", "plot_y", "action", "action_name", "event",
)  # fmt: skip


@dataclasses.dataclass
class ExplorationEvent:
    """Something an exploration step found: ``kind`` "ride" (a bus ridden from ``cell``; ``label``
    names its route by its stop: "A".."D" colored, "g1".."g4" gray), "map" (the map read at ``cell``)
    or "fridge" (``label`` "F<k>: <ingredient>", fridge k opened with pickup at ``cell``)."""

    step: int
    kind: str
    label: str
    cell: Cell


@dataclasses.dataclass
class ExplorationPath:
    """One trial's exploration episode: the agent's cells s_0..s_T (``cells``, T + 1 of them), its
    actions a_0..a_T-1 and what it found (``events``, in step order)."""

    problem_id: int
    cells: List[Cell]
    actions: List[int]
    events: List[ExplorationEvent]

    @property
    def length(self) -> int:
        """Exploration steps taken."""
        return len(self.actions)

    def labels(self, kind: str) -> List[str]:
        """The labels of the events of ``kind``, in order, each once."""
        return list(dict.fromkeys(e.label for e in self.events if e.kind == kind))


def _rgb(color: Tuple[int, int, int]) -> Tuple[float, float, float]:
    return tuple(c / 255 for c in color)  # type: ignore[return-value]


def _grid_env(env: gym.Env) -> TrialEnv:
    """``env.unwrapped`` if it is a grid family that these figures draw, else a ``ValueError``."""
    unwrapped = env.unwrapped
    if not isinstance(unwrapped, (MetaBusEnv, MetaCookEnv)):
        raise ValueError(
            f"env must be one of {', '.join(FAMILIES)} (grid worlds drawn from above), got {type(unwrapped).__name__}"
        )
    return unwrapped


class _PathRecorder(TrialRecorder):
    """Notes each exploration state's cell and each action; the trial's problem (read after the
    trial, never by the agent) then tells what the rides and pickups found."""

    def start_trial(self) -> None:
        self.states: List[np.ndarray] = []
        self.actions: List[int] = []
        self.closed = False

    def note(self, obs: Dict[str, Any], info: Dict[str, Any], action: int) -> None:
        if info.get("episode_end") and info.get("episode_phase") == EXPLORATION:
            self.states.append(np.asarray(info["final_obs"]).copy())  # the exploration's last state
            self.closed = True
        if int(obs["phase"]) == EXPLORATION:
            self.states.append(np.asarray(obs["obs"]).copy())
            self.actions.append(int(action))

    def trial_row(self, result: Dict[str, Any]) -> Tuple[Any, ...]:
        if not self.closed:  # a trial without an execution episode never shows the last state
            raise RuntimeError(
                "the exploration episode's last state was not seen: the trial needs an execution episode"
            )
        problem_id = int(result["problem_id"])
        cells = [(int(s[0]), int(s[1])) for s in self.states]
        events = _events(self.env, problem_id, self.states, self.actions)
        return (ExplorationPath(problem_id, cells, list(self.actions), events),)


def _events(
    env: TrialEnv, problem_id: int, states: Sequence[np.ndarray], actions: Sequence[int]
) -> List[ExplorationEvent]:
    """What each step of an exploration found, in problem ``problem_id``."""
    events: List[ExplorationEvent] = []
    if isinstance(env, MetaBusEnv):
        stop_of = bus_stop_of(env.routes(problem_id))
        map_read = False
        for t, action in enumerate(actions):
            cell = (int(states[t][0]), int(states[t][1]))
            if action == RIDE and int(states[t][2]) == BUS:
                stop = stop_of[cell]
                label = "ABCD"[COLORED_STOPS.index(stop)] if stop in COLORED_STOPS else f"g{GRAY_STOPS.index(stop) + 1}"
                events.append(ExplorationEvent(t, "ride", label, cell))
            if not map_read and shows_map(states[t + 1]):
                map_read = True
                events.append(ExplorationEvent(t, "map", "map", (int(states[t + 1][0]), int(states[t + 1][1]))))
    else:
        contents = fridge_contents(problem_id)
        for t, action in enumerate(actions):
            x, y = int(states[t][0]), int(states[t][1])
            k = fridge_picked(x, y, action)
            if k is not None:
                events.append(ExplorationEvent(t, "fridge", f"F{k}: {contents[k]}", (x, y)))
    return events


def held_out_problems(env: gym.Env, n: int, seed: int = 0, split: Optional[str] = None) -> np.ndarray:
    """``n`` problems of ``split`` (default: the env's), distinct while the split has enough,
    in an order drawn with ``seed``: the problems a figure's trials are pinned to."""
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n={n!r} must be a number of problems >= 1")
    ids = np.random.default_rng(seed).permutation(env.unwrapped.problem_ids(split))
    return np.resize(ids, n)


def exploration_paths(
    env: gym.Env,
    agent: ScriptedAgent,
    n_trials: int,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
) -> List[ExplorationPath]:
    """Play ``n_trials`` trials of ``agent`` in ``env`` (MetaBus-v0 or MetaCook-v0, pinned as in
    :func:`~dream_envs.play.play_trials`) and return each trial's exploration episode."""
    recorder = _PathRecorder(agent, _grid_env(env))
    return [recorder.trial_row(result)[0] for result in play_trials(env, recorder, n_trials, seed, problem_ids)]


def summary(env: gym.Env, paths: Sequence[ExplorationPath]) -> str:
    """One line on what the paths found: MetaBus, colored and gray routes ridden and map reads;
    MetaCook, fridges opened; with the mean exploration length."""
    grid = _grid_env(env)
    n = len(paths)
    length = np.mean([p.length for p in paths])
    if isinstance(grid, MetaBusEnv):
        rides = [p.labels("ride") for p in paths]
        colored = np.mean([sum(r in "ABCD" for r in ridden) for ridden in rides])
        parts = [f"colored routes {colored:.1f}"]
        if grid.variant == "distracting":
            parts.append(f"gray routes {np.mean([sum(r.startswith('g') for r in ridden) for ridden in rides]):.1f}")
        if grid.variant == "map":
            parts.append(f"map read in {sum(bool(p.labels('map')) for p in paths)}/{n}")
    else:
        opened = [len({e.label.split(":")[0] for e in p.events}) for p in paths]
        parts = [f"fridges opened {np.mean(opened):.1f} (all 3 in {sum(k == 3 for k in opened)}/{n})"]
    return ", ".join(parts) + f", {length:.1f} steps"


def _offsets(n: int, spread: float = 0.36) -> np.ndarray:
    """Per trial, the shift of its path along the cell's diagonal, so that trials stay apart."""
    if n == 1:
        return np.zeros(1)
    return np.linspace(-spread / 2, spread / 2, n)


def _plotted(cells: Sequence[Cell], offset: float) -> np.ndarray:
    return np.asarray(cells, dtype=float) + offset


def path_rows(env: gym.Env, panels: Mapping[str, Sequence[ExplorationPath]]) -> List[Tuple[Any, ...]]:
    """The points :func:`exploration_figure` plots, one row per panel, trial and exploration state
    (:data:`PATH_COLUMNS`): the cell, where it is drawn (with the trial's offset), the action taken
    there (empty at the last state) and what that step found."""
    names = getattr(env.unwrapped, "action_names", None) or ACTION_NAMES
    rows = []
    for panel, paths in panels.items():
        offsets = _offsets(len(paths))
        for k, path in enumerate(paths):
            found = {e.step: f"{e.kind} {e.label}" for e in path.events}
            for t, (x, y) in enumerate(path.cells):
                px, py = _plotted([(x, y)], offsets[k])[0]
                action = path.actions[t] if t < len(path.actions) else None
                rows.append((
                    panel, k, path.problem_id, t, x, y, round(float(px), 4), round(float(py), 4),
                    "" if action is None else action, "" if action is None else names[action], found.get(t, ""),
                ))  # fmt: skip
    return rows


def _cell_box(
    ax: Any, cell: Cell, face: Any, edge: Any = "none", lw: float = 0.0, inset: float = 0.04, **kw: Any
) -> None:
    from matplotlib.patches import Rectangle

    x, y = cell
    ax.add_patch(Rectangle((x - 0.5 + inset, y - 0.5 + inset), 1 - 2 * inset, 1 - 2 * inset,
                           facecolor=face, edgecolor=edge, linewidth=lw, zorder=1, **kw))  # fmt: skip


def _draw_grid(ax: Any, width: int, height: int) -> None:
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(-0.5, height - 0.5)
    ax.set_aspect("equal")
    for i in range(width + 1):
        ax.axvline(i - 0.5, color=_rgb(COLORS["grid"]), lw=0.6, zorder=0)
    for j in range(height + 1):
        ax.axhline(j - 0.5, color=_rgb(COLORS["grid"]), lw=0.6, zorder=0)
    ax.set_xticks(range(width))
    ax.set_yticks(range(height))
    ax.tick_params(length=0, labelsize=7)


def _draw_bus_layout(ax: Any, bus: MetaBusEnv) -> None:
    """The MetaBus grid without a problem: which stop leads where changes with the problem, so the
    stops carry their colour and letter, the destinations none (a ride's dashed arc shows where it led)."""
    _draw_grid(ax, SIZE, SIZE)
    for k, goal in enumerate(GOALS):
        _cell_box(ax, goal, (1.0, 0.94, 0.75))
        ax.text(*goal, f"goal{k + 1}", ha="center", va="center", fontsize=6, color="0.3", zorder=2)
    for i, stop in enumerate(COLORED_STOPS):
        _cell_box(ax, stop, _rgb(PALETTE[i]), inset=0.14, alpha=0.85)
        ax.text(*stop, "ABCD"[i], ha="center", va="center", fontsize=8, color="white", weight="bold", zorder=2)
    for dest in COLORED_DESTINATIONS:
        _cell_box(ax, dest, "none", edge="0.35", lw=1.2, inset=0.14)
        ax.text(dest[0], dest[1] - 0.3, "bus", ha="center", va="center", fontsize=5, color="0.35", zorder=2)
    if bus.variant == "distracting":
        for i, stop in enumerate(GRAY_STOPS):
            _cell_box(ax, stop, _rgb(COLORS["gray"]), inset=0.2, alpha=0.8)
            ax.text(*stop, f"g{i + 1}", ha="center", va="center", fontsize=6, color="white", zorder=2)
        for dest in GRAY_DESTINATIONS:
            _cell_box(ax, dest, "none", edge=_rgb(COLORS["gray"]), lw=1.0, inset=0.2)
    if bus.variant == "map":
        _cell_box(ax, MAP_CELL, _rgb(COLORS["teal"]), alpha=0.8)
        ax.text(MAP_CELL[0], MAP_CELL[1] - 0.3, "map", ha="center", va="center", fontsize=6, color="white", zorder=2)


def _draw_cook_layout(ax: Any, cook: MetaCookEnv) -> None:
    """The kitchen without a problem: the pot and the three fridges (their contents are the problem)."""
    _draw_grid(ax, GRID_SIZE, GRID_SIZE)
    _cell_box(ax, POT_POS, _rgb(COLORS["gray"]), alpha=0.5)
    ax.text(POT_POS[0], POT_POS[1] - 0.38, "pot", ha="center", va="center", fontsize=8, color="0.2", zorder=2)
    for k, cell in enumerate(FRIDGE_POS):
        _cell_box(ax, cell, (0.85, 0.92, 1.0), edge="0.4", lw=1.0)
        ax.text(cell[0] + 0.38, cell[1] - 0.38, f"F{k}", ha="right", va="center", fontsize=8, color="0.2", zorder=2)


def draw_explorations(ax: Any, env: gym.Env, paths: Sequence[ExplorationPath], title: Optional[str] = None) -> None:
    """Draw the grid of ``env`` on the matplotlib axes ``ax`` and ``paths`` over it: one colour and
    one diagonal offset per trial, an arrow per move, a dashed arc per bus ride (the cell it led
    to), a circle at the start, a cross at the end, a star where a bus was ridden or a fridge
    opened and a ring where the map was read. The legend lists each trial's problem and findings."""
    from matplotlib.lines import Line2D

    grid = _grid_env(env)
    (_draw_bus_layout if isinstance(grid, MetaBusEnv) else _draw_cook_layout)(ax, grid)  # type: ignore[operator]
    offsets = _offsets(len(paths), 0.36 if isinstance(grid, MetaBusEnv) else 0.5)
    colors = _trial_colors(len(paths))
    handles = []
    for k, path in enumerate(paths):
        color = colors[k]
        points = _plotted(path.cells, offsets[k])
        for t, action in enumerate(path.actions):
            src, dst = points[t], points[t + 1]
            if np.allclose(src, dst):
                continue
            ride = action == RIDE and isinstance(grid, MetaBusEnv)
            ax.annotate("", xy=dst, xytext=src, zorder=4, arrowprops=dict(
                arrowstyle="-|>", color=color, lw=1.4, mutation_scale=9, shrinkA=0, shrinkB=0,
                linestyle="--" if ride else "-", connectionstyle="arc3,rad=0.25" if ride else "arc3",
            ))  # fmt: skip
        ax.plot(*points[0], "o", ms=6, mfc="white", mec=color, mew=1.8, zorder=6)
        ax.plot(*points[-1], "X", ms=8, color=color, mec="black", mew=0.6, zorder=6)
        for event in path.events:
            at = _plotted([event.cell], offsets[k])[0]
            if event.kind == "map":
                ax.plot(*at, "o", ms=16, mfc="none", mec=color, mew=2.0, zorder=5)
            else:
                ax.plot(*at, "*", ms=12, color=color, mec="black", mew=0.6, zorder=7)
        handles.append(Line2D([], [], color=color, lw=2, label=_trial_label(grid, path)))
    markers = [
        Line2D([], [], ls="none", marker="o", mfc="white", mec="0.2", label="start"),
        Line2D([], [], ls="none", marker="X", color="0.2", label="end"),
        Line2D([], [], ls="none", marker="*", ms=10, color="0.2",
               label="bus ridden" if isinstance(grid, MetaBusEnv) else "fridge opened"),
    ]  # fmt: skip
    if isinstance(grid, MetaBusEnv):
        markers.append(Line2D([], [], ls="--", color="0.2", label="ride"))
        if grid.variant == "map":
            markers.append(Line2D([], [], ls="none", marker="o", ms=10, mfc="none", mec="0.2", label="map read"))
    wide = max((len(h.get_label()) for h in handles), default=0) > 44  # two columns would overrun the panel
    ax.legend(handles=handles + markers, loc="upper center", bbox_to_anchor=(0.5, -0.06), fontsize=7,
              ncol=1 if wide else 2, frameon=False)  # fmt: skip
    if title is not None:
        ax.set_title(title, fontsize=9)


def _trial_colors(n: int) -> List[Any]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(k % cmap.N) for k in range(n)]


def _trial_label(grid: TrialEnv, path: ExplorationPath) -> str:
    """The legend entry of one trial: its problem and what its exploration found."""
    if isinstance(grid, MetaBusEnv):
        found = [f"rode {', '.join(path.labels('ride'))}" if path.labels("ride") else "no ride"]
        if grid.variant == "map":
            found.append("read map" if path.labels("map") else "no map")
    else:
        # the problem's contents are in the label already: name the fridges, in the order opened
        opened = [label.split(":")[0] for label in path.labels("fridge")]
        found = [f"opened {', '.join(opened)}" if opened else "no fridge"]
        return f"problem {path.problem_id} {fridge_contents(path.problem_id)}: {', '.join(found)} ({path.length} steps)"
    return f"problem {path.problem_id}: {', '.join(found)} ({path.length} steps)"


def exploration_figure(
    env: gym.Env,
    panels: Mapping[str, Sequence[ExplorationPath]],
    out: Optional[Union[str, pathlib.Path]] = None,
    title: Optional[str] = None,
) -> Any:
    """A matplotlib figure with one panel per entry of ``panels`` (its label -> its agent's paths),
    side by side, each titled with its label and :func:`summary`; saved to ``out`` if given."""
    import matplotlib

    if out is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if not panels:
        raise ValueError("panels must hold at least one agent's paths")
    n_trials = max(len(p) for p in panels.values())
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 5.6 + 0.18 * n_trials), squeeze=False)
    for ax, (label, paths) in zip(axes[0], panels.items()):
        draw_explorations(ax, env, paths, title=f"{label}\n{summary(env, paths)}")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    if out is not None:
        fig.savefig(out, dpi=120, bbox_inches="tight")
        plt.close(fig)
    return fig
