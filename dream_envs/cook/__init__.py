"""MetaCook-v0: the paper's cooking domain (Section 6.1, Figure 4b, Appendix B.1).

* :mod:`~dream_envs.cook.kitchen`: the kitchen's layout, problems, recipes, splits and rules;
* :mod:`~dream_envs.cook.env`: :class:`MetaCookEnv`, the trial env;
* :mod:`~dream_envs.cook.oracle`: :class:`CookOracle`, the scripted optimal agent;
* :mod:`~dream_envs.cook.report`: :func:`behaviour_report`.
"""

# The grid actions and the object codes are MetaBus's: this package's names for them.
from dream_envs.bus import ACTION_NAMES as GRID_ACTION_NAMES
from dream_envs.bus import (
    DOWN,
    DROP,
    END_EPISODE,
    FRIDGE,
    LEFT,
    MOVES,
    N_ACTIONS,
    NO_OBJECT,
    NOOP,
    PICKUP,
    POT,
    RIGHT,
    UP,
)
from dream_envs.bus import RIDE as RIDE_BUS
from dream_envs.cook.env import MetaCookEnv
from dream_envs.cook.kitchen import (
    COOK_SPLITS,
    DONE_STAGE,
    FRIDGE_POS,
    GRID_SIZE,
    HELD_OUT_INSTRUCTIONS,
    HELD_OUT_PROBLEMS,
    HELD_OUT_SEED,
    N_FRIDGES,
    N_HELD_OUT_PROBLEMS,
    N_INGREDIENTS,
    N_PROBLEMS,
    POT_POS,
    RUINED,
    STAGE_REWARD,
    START,
    STEP_REWARD,
    UNDO_REWARD,
    cook_transition,
    distance_to_fridge,
    first_openings,
    fridge_contents,
    fridge_picked,
    object_at,
    opening_rewards,
    optimal_execution_return,
    problem_id_of,
    recipe_stage,
    valid_instructions,
)
from dream_envs.cook.oracle import CookOracle
from dream_envs.cook.report import CookReport, behaviour_report

__all__ = [
    "COOK_SPLITS",
    "DONE_STAGE",
    "DOWN",
    "DROP",
    "END_EPISODE",
    "FRIDGE",
    "FRIDGE_POS",
    "GRID_ACTION_NAMES",
    "GRID_SIZE",
    "HELD_OUT_INSTRUCTIONS",
    "HELD_OUT_PROBLEMS",
    "HELD_OUT_SEED",
    "LEFT",
    "MOVES",
    "NOOP",
    "NO_OBJECT",
    "N_ACTIONS",
    "N_FRIDGES",
    "N_HELD_OUT_PROBLEMS",
    "N_INGREDIENTS",
    "N_PROBLEMS",
    "PICKUP",
    "POT",
    "POT_POS",
    "RIDE_BUS",
    "RIGHT",
    "RUINED",
    "STAGE_REWARD",
    "START",
    "STEP_REWARD",
    "UNDO_REWARD",
    "UP",
    "CookOracle",
    "CookReport",
    "MetaCookEnv",
    "behaviour_report",
    "cook_transition",
    "distance_to_fridge",
    "first_openings",
    "fridge_contents",
    "fridge_picked",
    "object_at",
    "opening_rewards",
    "optimal_execution_return",
    "problem_id_of",
    "recipe_stage",
    "valid_instructions",
]
