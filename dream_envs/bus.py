"""MetaBus-v0: the paper's "distracting bus" and "map" grid worlds (Section 5.1, Appendix B.1)."""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from gymnasium import spaces

from dream_envs.agents import ScriptedAgent
from dream_envs.checks import check_choice
from dream_envs.rendering import COLORS, PALETTE, GridCanvas
from dream_envs.report import TrialRecorder, record_trials, unwrap
from dream_envs.trial_env import EXPLORATION, TrialEnv

Cell = Tuple[int, int]

# Grid actions shared by the grid families (bus, cooking).
LEFT, UP, RIGHT, DOWN, NOOP, RIDE, END_EPISODE, PICKUP, DROP = range(9)
N_ACTIONS = 9
ACTION_NAMES = ("left", "up", "right", "down", "noop", "ride", "end", "pickup", "drop")
MOVES: Dict[int, Cell] = {LEFT: (-1, 0), UP: (0, 1), RIGHT: (1, 0), DOWN: (0, -1)}
# Object under the agent (third ``obs`` dimension), shared by the grid families.
NO_OBJECT, BUS, MAP, POT, FRIDGE = range(5)
N_OBJECTS = 5

SIZE = 9
START: Cell = (4, 4)
COLORED_STOPS: Tuple[Cell, ...] = ((4, 5), (5, 4), (3, 4), (4, 3))
COLORED_DESTINATIONS: Tuple[Cell, ...] = ((0, 1), (0, 7), (8, 1), (8, 7))
GRAY_STOPS: Tuple[Cell, ...] = ((5, 5), (3, 3), (3, 5), (5, 3))
GRAY_DESTINATIONS: Tuple[Cell, ...] = ((0, 4), (4, 0), (8, 4), (4, 8))
# Instruction k + 1 asks for GOALS[k].
GOALS: Tuple[Cell, ...] = ((0, 0), (8, 8), (0, 8), (8, 0))
MAP_CELL: Cell = (7, 3)
PERMUTATIONS: Tuple[Tuple[int, ...], ...] = tuple(itertools.permutations(range(4)))
VARIANTS = ("distracting", "map", "vanilla")
TRAIN_EVERY = 11  # distracting bus: problems 0, 11, 22, ... are the training split

STEP_REWARD = -0.1
GOAL_REWARD = 1.0


def goal_stop_destination(goal_index: int) -> Cell:
    """The colored-bus destination next to goal ``goal_index`` (one step from it)."""
    gx, gy = GOALS[goal_index]
    (dest,) = [d for d in COLORED_DESTINATIONS if abs(d[0] - gx) + abs(d[1] - gy) == 1]
    return dest


class MetaBusEnv(TrialEnv):
    """Reach the instructed corner of a 9x9 grid, fastest by riding the right colored bus.

    The agent starts every inner episode at (4, 4), next to four colored bus stops
    (4, 5), (5, 4), (3, 4) and (4, 3). Riding a colored bus teleports the agent to one of
    (0, 1), (0, 7), (8, 1), (8, 7), each one step from a goal corner; which stop goes where is the
    problem, so an agent that explored the buses reaches any goal in 3 steps, and one that did not
    walks 8 steps. Bus links are two-way: riding at a destination returns to its stop.

    **Variants** (``variant``):

    * ``"distracting"`` (default, the paper's *distracting bus*): four gray buses at (5, 5), (3, 3),
      (3, 5), (5, 3) lead to a permutation of (0, 4), (4, 0), (8, 4), (4, 8). They are part of the
      problem but useless for any instruction. 576 problems: ID = colored permutation index
      + 24 x gray permutation index (``itertools.permutations`` order); ``train`` = IDs 0, 11, 22,
      ... (53 problems), ``test`` = the other 523, ``all`` = all 576.
    * ``"map"`` (the paper's *map*): no gray buses; standing on the map at (7, 3) shows the colored
      permutation in a fourth ``obs`` dimension. 24 problems, all in every split.
    * ``"vanilla"``: no gray buses, no map. 24 problems, all in every split.

    **Instruction.** ``[k + 1]`` asks to reach ``GOALS[k]``, with GOALS = (0, 0), (8, 8), (0, 8),
    (8, 0), drawn uniformly; ``[0]`` = none (reward-free exploration).

    **Actions.** ``Discrete(9)``: 0 left (x - 1), 1 up (y + 1), 2 right (x + 1), 3 down (y - 1),
    4 no-op, 5 ride the bus under the agent (no-op elsewhere), 6 end the inner episode (the trial's
    end-episode action), 7 pickup and 8 drop (no-ops here; kept so all grid families share the action
    set). Moves are clipped at the border.

    **Observation** ``obs``: ``MultiDiscrete([9, 9, 5])`` = ``[x, y, object under the agent]``
    (0 none, 1 bus, 2 map; 3 pot and 4 fridge exist only in the cooking family). The map variant
    adds a fourth dimension (``MultiDiscrete([9, 9, 5, 25])``): 0 off the map, 1 + the colored
    permutation index on it.

    **Rewards and termination.** In an execution episode every step costs -0.1, except the step
    that reaches the instructed goal, which earns +1 and ends the episode. The end-episode action
    ends it at a cost of -0.1 per remaining step (itself included), so quitting never beats
    wandering. Inner episodes last at most ``horizon`` steps. In reward-free exploration every
    reward is 0 and the corners end nothing. Optimal execution return: 0.8 (stop, ride, goal);
    walking without information: 0.3.

    :param variant: "distracting", "map" or "vanilla".
    :param horizon: the inner-episode horizon (default 20, the paper's).
    """

    action_names = ACTION_NAMES

    def __init__(
        self,
        variant: str = "distracting",
        split: str = "train",
        n_exec_episodes: int = 1,
        horizon: int = 20,
        reward_free_exploration: bool = True,
        render_mode: Optional[str] = None,
        final_frames: bool = False,
    ) -> None:
        self.variant = check_choice("variant", variant, VARIANTS)
        nvec = [SIZE, SIZE, N_OBJECTS] + ([len(PERMUTATIONS) + 1] if variant == "map" else [])
        super().__init__(
            inner_observation_space=spaces.MultiDiscrete(nvec),
            instruction_nvec=[len(GOALS) + 1],
            n_actions=N_ACTIONS,
            end_episode_action=END_EPISODE,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=horizon,
            reward_free_exploration=reward_free_exploration,
            render_mode=render_mode,
            final_frames=final_frames,
        )
        self._n_problems = len(PERMUTATIONS) ** (2 if variant == "distracting" else 1)
        self._links: Dict[Cell, Cell] = {}
        self._pos: Cell = START

    # ------------------------------------------------------------------ the problem family
    @property
    def n_problems(self) -> int:
        return self._n_problems

    def _split_problem_ids(self, split: str) -> np.ndarray:
        ids = np.arange(self._n_problems)
        if self.variant != "distracting" or split == "all":
            return ids
        is_train = ids % TRAIN_EVERY == 0
        return ids[is_train] if split == "train" else ids[~is_train]

    @property
    def problem_nvec(self) -> np.ndarray:
        # Appendix B.1: the colored permutation, plus (distracting) where each gray bus leads.
        n = len(PERMUTATIONS)
        return np.array([n] + ([4, 4, 4, 4] if self.variant == "distracting" else []), dtype=np.int64)

    def problem_features(self, problem_id: int) -> np.ndarray:
        """``[colored permutation index]`` (+ ``[gray destination index of each gray bus]`` when distracting)."""
        n = len(PERMUTATIONS)
        gray = list(PERMUTATIONS[problem_id // n]) if self.variant == "distracting" else []
        return np.array([problem_id % n, *gray], dtype=np.int64)

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        # Every goal is valid in every problem and split: generalisation is over problems only.
        return np.arange(1, len(GOALS) + 1).reshape(-1, 1)

    def routes(self, problem_id: int) -> Dict[Cell, Cell]:
        """Where each bus stop of problem ``problem_id`` leads (colored stops first, then gray ones)."""
        valid = isinstance(problem_id, (int, np.integer)) and not isinstance(problem_id, (bool, np.bool_))
        if not (valid and 0 <= problem_id < self.n_problems):
            raise ValueError(
                f"problem_id={problem_id!r} is not valid; accepted values: integers 0 .. {self.n_problems - 1}"
            )
        colored = PERMUTATIONS[problem_id % len(PERMUTATIONS)]
        routes = {stop: COLORED_DESTINATIONS[d] for stop, d in zip(COLORED_STOPS, colored)}
        if self.variant == "distracting":
            gray = PERMUTATIONS[problem_id // len(PERMUTATIONS)]
            routes.update({stop: GRAY_DESTINATIONS[d] for stop, d in zip(GRAY_STOPS, gray)})
        return routes

    def _set_problem(self, problem_id: int) -> None:
        self._routes = self.routes(problem_id)
        self._links = dict(self._routes)
        self._links.update({dest: stop for stop, dest in self._routes.items()})  # two-way
        self._map_value = 1 + problem_id % len(PERMUTATIONS)

    # ------------------------------------------------------------------ the inner MDP
    def _state(self) -> np.ndarray:
        pos = self._pos
        if pos in self._links:
            obj = BUS
        elif self.variant == "map" and pos == MAP_CELL:
            obj = MAP
        else:
            obj = NO_OBJECT
        state = [pos[0], pos[1], obj]
        if self.variant == "map":
            state.append(self._map_value if pos == MAP_CELL else 0)
        return np.array(state, dtype=np.int64)

    def _inner_reset(self) -> np.ndarray:
        self._pos = START
        return self._state()

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        if action in MOVES:
            dx, dy = MOVES[action]
            self._pos = (min(max(self._pos[0] + dx, 0), SIZE - 1), min(max(self._pos[1] + dy, 0), SIZE - 1))
        elif action == RIDE and self._pos in self._links:
            self._pos = self._links[self._pos]
        if self.instruction is None:
            return self._state(), 0.0, False
        if self._pos == GOALS[int(self.instruction[0]) - 1]:
            return self._state(), GOAL_REWARD, True
        return self._state(), STEP_REWARD, False

    def _end_episode_reward(self, steps_remaining: int) -> float:
        return STEP_REWARD * steps_remaining

    # ------------------------------------------------------------------ picture
    def _render_frame(self) -> np.ndarray:
        canvas = GridCanvas(SIZE, SIZE, cell=56, caption_lines=2)
        goal = None if self.instruction is None else int(self.instruction[0]) - 1
        for k, (gx, gy) in enumerate(GOALS):
            canvas.fill(gx, gy, COLORS["goal"] if k == goal else (250, 240, 190))
            canvas.text(gx, gy, f"goal{k + 1}", scale=0.4)
            if k == goal:
                canvas.square(gx, gy, COLORS["agent"], scale=0.95, thickness=3)
        # A stop is a filled square, its destination an outlined one of the same colour and label.
        for i, stop in enumerate(COLORED_STOPS):
            color, label = PALETTE[i], "ABCD"[i]
            dest = self._routes[stop]
            canvas.square(*stop, color, scale=0.8)
            canvas.text(*stop, label, (255, 255, 255), scale=0.6)
            canvas.square(*dest, color, scale=0.8, thickness=4)
            canvas.text(*dest, label, color, scale=0.6)
        for i, stop in enumerate(GRAY_STOPS):
            if stop in self._routes:
                canvas.square(*stop, COLORS["gray"], scale=0.6)
                canvas.text(*stop, f"g{i + 1}", (255, 255, 255), scale=0.4)
                canvas.square(*self._routes[stop], COLORS["gray"], scale=0.6, thickness=3)
                canvas.text(*self._routes[stop], f"g{i + 1}", COLORS["gray"], scale=0.4)
        if self.variant == "map":
            canvas.fill(*MAP_CELL, COLORS["teal"])
            canvas.text(*MAP_CELL, "map", (255, 255, 255))
        canvas.agent(*self._pos)
        if self.phase == EXPLORATION:
            phase = "exploration episode"
        else:
            phase = f"execution episode {self.episode_index}/{self.n_exec_episodes}"
        canvas.caption(f"MetaBus {self.variant}, problem {self.problem_id}: {phase}, step {self._t}/{self.horizon}")
        if goal is None:
            canvas.caption("instruction: none (reward-free exploration)")
        else:
            canvas.caption(f"instruction {goal + 1}: reach goal{goal + 1} at {GOALS[goal]}")
        return canvas.frame()

    # ------------------------------------------------------------------ oracle
    def oracle(self) -> "BusOracle":
        return BusOracle(self.variant)


class BusOracle(ScriptedAgent):
    """Optimal scripted agent: learns the colored routes while exploring, then rides to the goal.

    Exploration (default 20-step horizon): in the map variant it walks to the map (4 steps), reads
    it and ends the episode; otherwise it rides three colored buses, riding back after each of the
    first two (10 steps), infers the fourth route and ends the episode. Execution: step onto the
    stop whose destination is next to the instructed goal, ride, step onto the goal (return 0.8).
    It only uses what it observed; if it knows too little (a horizon too short to explore), it
    walks to the goal instead.
    """

    # Up onto (4, 5), ride there and back, down, right onto (5, 4), ride there and back, left twice
    # onto (3, 4), ride: three routes seen. Entries are (action, colored stop ridden or None).
    _RIDE_PLAN: Tuple[Tuple[int, Optional[int]], ...] = (
        (UP, None), (RIDE, 0), (RIDE, None), (DOWN, None), (RIGHT, None), (RIDE, 1),
        (RIDE, None), (LEFT, None), (LEFT, None), (RIDE, 2),
    )  # fmt: skip
    _MAP_PLAN: Tuple[Tuple[int, Optional[int]], ...] = ((RIGHT, None), (RIGHT, None), (RIGHT, None), (DOWN, None))

    def __init__(self, variant: str = "distracting") -> None:
        self.variant = check_choice("variant", variant, VARIANTS)
        self.reset()

    def reset(self) -> None:
        self.routes: Dict[int, Cell] = {}  # colored stop index -> destination
        self._plan_step = 0
        self._pending_ride: Optional[int] = None

    def _observe(self, state: Sequence[int]) -> None:
        pos = (int(state[0]), int(state[1]))
        if self._pending_ride is not None:
            self.routes[self._pending_ride] = pos
            self._pending_ride = None
        if self.variant == "map" and len(state) > 3 and int(state[3]) > 0:
            perm = PERMUTATIONS[int(state[3]) - 1]
            self.routes = {i: COLORED_DESTINATIONS[d] for i, d in enumerate(perm)}
        if len(self.routes) == len(COLORED_STOPS) - 1:  # the last route is the one left over
            (stop,) = set(range(len(COLORED_STOPS))) - set(self.routes)
            (dest,) = set(COLORED_DESTINATIONS) - set(self.routes.values())
            self.routes[stop] = dest

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        if info.get("episode_end"):
            # The step already returned the next episode's first state: the state a ride led to
            # (if the ride was the episode's last step) is only in final_obs.
            self._observe(info["final_obs"])
            self._pending_ride = None
        self._observe(obs["obs"])
        if int(obs["phase"]) == EXPLORATION:
            return self._explore()
        return self._execute(obs)

    def _explore(self) -> int:
        plan = self._MAP_PLAN if self.variant == "map" else self._RIDE_PLAN
        if len(self.routes) == len(COLORED_STOPS) or self._plan_step >= len(plan):
            return END_EPISODE
        action, ridden = plan[self._plan_step]
        self._plan_step += 1
        self._pending_ride = ridden
        return action

    def _execute(self, obs: Dict[str, Any]) -> int:
        goal_index = int(obs["instruction"][0]) - 1
        if goal_index < 0:  # no instruction: nothing to do
            return NOOP
        pos = (int(obs["obs"][0]), int(obs["obs"][1]))
        near_goal = goal_stop_destination(goal_index)
        stops = [COLORED_STOPS[i] for i, dest in self.routes.items() if dest == near_goal]
        if pos == near_goal or not stops:
            return _step_towards(pos, GOALS[goal_index])
        if pos == stops[0]:
            return RIDE
        return _step_towards(pos, stops[0])


@dataclasses.dataclass
class BusExplorationReport:
    """What an agent did in MetaBus exploration episodes, one entry per trial (the paper's Figure 7
    in numbers): how many colored and gray routes it rode, whether it read the map, and what the
    exploration led to.

    A route counts as seen once the agent rides its bus from either end. Three colored routes
    determine the fourth; the gray ones never help. An execution episode that misses the goal
    (the horizon, or the end-episode action, ends it first) returns exactly ``-0.1 x horizon``.
    """

    colored_routes: np.ndarray  # [n_trials] 0..4
    gray_routes: np.ndarray  # [n_trials] 0..4
    read_map: np.ndarray  # [n_trials] bool (map variant; False elsewhere)
    exploration_lengths: np.ndarray  # [n_trials]
    execution_returns: np.ndarray  # [n_trials] mean over the trial's execution episodes
    variant: str = "distracting"
    goal_missed: Optional[np.ndarray] = None  # [n_trials] share of its execution episodes that missed the goal

    def summary(self) -> str:
        counts = np.bincount(self.colored_routes, minlength=len(COLORED_STOPS) + 1)
        parts = [f"colored routes seen {self.colored_routes.mean():.2f} (trials with 0..4: {counts.tolist()})"]
        if self.variant == "distracting":
            parts.append(f"gray routes {self.gray_routes.mean():.2f}")
        if self.variant == "map":
            parts.append(f"map read {self.read_map.mean():.0%}")
        parts.append(f"exploration length {self.exploration_lengths.mean():.1f}")
        parts.append(f"execution return {self.execution_returns.mean():.3f}")
        if self.goal_missed is not None:
            parts.append(f"goal missed in {self.goal_missed.mean():.1%} of execution episodes")
        by_routes = "; ".join(
            f"{k}: {mean:.3f} ({n} trials)" for k, (n, mean) in self.returns_by_colored_routes().items()
        )
        return ", ".join(parts) + f"; execution return by colored routes seen: {by_routes}"

    def returns_by_colored_routes(self) -> Dict[int, Tuple[int, float]]:
        """Number of trials and mean execution return for each number of colored routes seen (only
        the numbers that occur): what the exploration's coverage is worth to the execution policy."""
        groups = {int(k): self.execution_returns[self.colored_routes == k] for k in np.unique(self.colored_routes)}
        return {k: (len(returns), float(returns.mean())) for k, returns in groups.items()}


class _ExplorationRecorder(TrialRecorder):
    """Notes the cells the agent rides at and whether it reads the map while exploring, and turns
    them, with the trial's problem (never shown to the agent), into the routes it saw."""

    env: MetaBusEnv

    def start_trial(self) -> None:
        self.rides: List[Cell] = []
        self.read_map = False

    def note(self, obs: Dict[str, Any], info: Dict[str, Any], action: int) -> None:
        if info.get("episode_end") and info.get("episode_phase") == EXPLORATION:
            self._note_map(info["final_obs"])  # the exploration episode's last state
        if int(obs["phase"]) == EXPLORATION:
            self._note_map(obs["obs"])
            if action == RIDE and int(obs["obs"][2]) == BUS:
                self.rides.append((int(obs["obs"][0]), int(obs["obs"][1])))

    def _note_map(self, state: np.ndarray) -> None:
        self.read_map |= shows_map(state)

    def trial_row(self, result: Dict[str, Any]) -> Tuple[Any, ...]:
        stop_of = bus_stop_of(self.env.routes(int(result["problem_id"])))
        seen = {stop_of[cell] for cell in self.rides}
        missed_return = STEP_REWARD * self.env.horizon  # every step's cost, no goal reward
        return (
            len(seen & set(COLORED_STOPS)),
            len(seen & set(GRAY_STOPS)),
            self.read_map,
            result["exploration_length"],
            float(np.mean(result["execution_returns"])),
            float(np.mean(np.isclose(result["execution_returns"], missed_return))),
        )


def shows_map(state: np.ndarray) -> bool:
    """Whether the inner state ``state`` shows the map.

    Only the map variant's states have a fourth dimension, set while the agent stands on the map
    cell (it then holds the index + 1 of the problem's colored permutation); other variants never
    show it.

    :param state: one inner state ``obs`` (``[x, y, cell kind]``, plus the map entry in the map variant).
    :return: True when the state carries the map.
    """
    return len(state) > 3 and int(state[3]) > 0


def bus_stop_of(routes: Dict[Cell, Cell]) -> Dict[Cell, Cell]:
    """The route each bus cell belongs to, named by the route's stop.

    A route joins a stop and its destination, and riding from either end reveals the same route,
    so both cells map to the stop: ``bus_stop_of(env.routes(problem_id))[cell]`` tells which
    route a ride from ``cell`` saw.

    :param routes: one problem's routes, ``{stop: destination}`` (:meth:`MetaBusEnv.routes`).
    :return: ``{cell: stop}`` for every stop and destination cell.
    """
    return {**{stop: stop for stop in routes}, **{dest: stop for stop, dest in routes.items()}}


def exploration_report(
    env: MetaBusEnv,
    agent: ScriptedAgent,
    n_trials: int = 100,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
) -> BusExplorationReport:
    """Play ``n_trials`` trials of ``agent`` (a :class:`~dream_envs.agents.ScriptedAgent`; for a model
    use ``sb3_dream.evaluation.as_trial_agent(model)``) and report its exploration.

    The problem ID is read from the env's ``info`` after each trial, to resolve which routes the
    rides revealed; the agent never sees it. ``problem_ids`` pins trial k to
    ``problem_ids[k % len(problem_ids)]``, and ``instructions`` (one per problem ID) its
    execution episodes' instruction likewise.
    """
    bus = unwrap(env, MetaBusEnv, "MetaBus-v0")
    trials, _ = record_trials(env, _ExplorationRecorder(agent, bus), n_trials, seed, problem_ids, instructions)
    colored, gray, read_map, lengths, returns, missed = trials
    return BusExplorationReport(colored, gray, read_map.astype(bool), lengths, returns, bus.variant, missed)


DISCOVERIES = ("colored route", "gray route", "route again", "map", "other")


def discovery_rewards(
    env: MetaBusEnv,
    trajectories: Sequence[Tuple[np.ndarray, np.ndarray]],
    rewards: Sequence[np.ndarray],
    problem_ids: Sequence[int],
) -> Dict[str, np.ndarray]:
    """The rewards of exploration steps by what they found, over trajectories (states, actions) of
    ``problem_ids`` and their per-step ``rewards`` (DREAM's: ``sb3_dream.dream.exploration_gains``):
    a ride on a colored or gray route not ridden before in the trajectory (from either end, as in
    :class:`BusExplorationReport`), a ride on one ridden before ("route again"), the step onto the
    map (map variant, its first time), and every other step. Keys in :data:`DISCOVERIES` order,
    only those that occur."""
    bus = unwrap(env, MetaBusEnv, "MetaBus-v0")
    found: Dict[str, List[float]] = {kind: [] for kind in DISCOVERIES}
    for (states, actions), reward, problem_id in zip(trajectories, rewards, problem_ids):
        stop_of = bus_stop_of(bus.routes(int(problem_id)))
        ridden, map_read = set(), False
        for t, action in enumerate(actions):
            cell = (int(states[t][0]), int(states[t][1]))
            if action == RIDE and int(states[t][2]) == BUS:
                stop = stop_of[cell]
                kind = "route again" if stop in ridden else "colored route" if stop in COLORED_STOPS else "gray route"
                ridden.add(stop)
            elif not map_read and shows_map(states[t + 1]):
                kind, map_read = "map", True
            else:
                kind = "other"
            found[kind].append(float(reward[t]))
    return {kind: np.array(values) for kind, values in found.items() if values}


def _step_towards(pos: Cell, target: Cell) -> int:
    """A move that brings ``pos`` one step closer to ``target`` (x first), or no-op if there."""
    if pos[0] != target[0]:
        return RIGHT if target[0] > pos[0] else LEFT
    if pos[1] != target[1]:
        return UP if target[1] > pos[1] else DOWN
    return NOOP
