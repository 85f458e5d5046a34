"""MetaCook's scripted optimal agent: open every fridge, then cook from memory."""

from __future__ import annotations

from typing import Any, Dict, Tuple

from dream_envs.agents import ScriptedAgent
from dream_envs.bus import DOWN, DROP, END_EPISODE, FRIDGE, LEFT, PICKUP, RIGHT, UP
from dream_envs.cook.kitchen import FRIDGE_POS, N_FRIDGES, POT_POS, distance_to_fridge, recipe_stage
from dream_envs.trial_env import EXPLORATION


def _step_towards(x: int, y: int, target: Tuple[int, int]) -> int:
    """First move of a shortest path (x first, then y)."""
    tx, ty = target
    if x != tx:
        return RIGHT if tx > x else LEFT
    return UP if ty > y else DOWN


class CookOracle(ScriptedAgent):
    """Optimal scripted agent: open every fridge, then cook from memory.

    Exploration: go to the nearest unopened fridge and pick up there (right, pickup, down, pickup,
    up, up, pickup: 7 steps), then the end-episode action. A pickup's result is read from the
    inventory of the next observation or, when that step ended the episode, from
    ``info["final_obs"]``. Execution: for each ingredient still needed, go to the nearest fridge
    known to hold it, pick up, return to the pot and drop; this is optimal (see
    :func:`optimal_execution_return`). If the exploration was cut short, an ingredient missing from
    the opened fridges is in an unopened one: the only one, or else the nearest is opened.

    (Opening the middle fridge and one corner one would already suffice for optimal execution:
    recipes use only present ingredients and both corners are 2 steps from the pot. The oracle
    opens all three, like DREAM's learned exploration in the paper's Figure 8.)
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.known: Dict[int, int] = {}  # fridge index -> ingredient

    def _observe(self, obs: Dict[str, Any], info: Dict[str, Any]) -> None:
        if int(obs["prev_action"]) - 1 != PICKUP:
            return
        # The state reached by the pickup: the episode's last one if that step ended it.
        state = info["final_obs"] if info.get("episode_end") else obs["obs"]
        x, y, obj, inventory = (int(v) for v in state[:4])
        if obj == FRIDGE and inventory:
            self.known[y] = inventory

    def _fridge_for(self, ingredient: int, x: int, y: int) -> Tuple[int, bool]:
        """The fridge to fetch ``ingredient`` from, and whether it is known to hold it."""
        dist = lambda k: abs(FRIDGE_POS[k][0] - x) + abs(FRIDGE_POS[k][1] - y)  # noqa: E731
        holding = [k for k, c in self.known.items() if c == ingredient]
        unknown = [k for k in range(N_FRIDGES) if k not in self.known]
        if holding:
            # Nearest to the pot, where every fetch starts and ends.
            return min(holding, key=distance_to_fridge), True
        if len(unknown) == 1:
            return unknown[0], True
        return min(unknown or range(N_FRIDGES), key=dist), False

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        self._observe(obs, info)
        x, y, _, inventory, pot1, pot2 = (int(v) for v in obs["obs"])
        if int(obs["phase"]) == EXPLORATION:
            unknown = [k for k in range(N_FRIDGES) if k not in self.known]
            if not unknown:
                return END_EPISODE
            target = min(unknown, key=lambda k: abs(FRIDGE_POS[k][0] - x) + abs(FRIDGE_POS[k][1] - y))
            return PICKUP if (x, y) == FRIDGE_POS[target] else _step_towards(x, y, FRIDGE_POS[target])

        a, b = (int(i) for i in obs["instruction"])
        stage = recipe_stage(inventory, (pot1, pot2), (a, b))
        if stage in (1, 3):  # holding the next ingredient: bring it to the pot
            return DROP if (x, y) == POT_POS else _step_towards(x, y, POT_POS)
        if stage in (0, 2):  # fetch the next ingredient
            fridge, _ = self._fridge_for(a if stage == 0 else b, x, y)
            target = FRIDGE_POS[fridge]
            return PICKUP if (x, y) == target else _step_towards(x, y, target)
        return END_EPISODE  # ruined dish (never by this agent): nothing left to earn
