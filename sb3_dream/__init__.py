"""sb3-dream: DREAM and the paper's meta-RL baselines (RL², IMPORT, VariBAD) for Stable-Baselines3."""

import dream_envs  # noqa: F401  (registers the meta-RL envs so env IDs resolve)
from sb3_dream.dream import DREAM, DreamPolicy
from sb3_dream.evaluation import MetaEvalCallback, evaluate_meta
from sb3_dream.import_dqn import IMPORT
from sb3_dream.presets import PRESETS
from sb3_dream.rl2dqn import RL2DQN
from sb3_dream.varibad import VariBAD
from sb3_dream.version import __version__

__all__ = [
    "DREAM",
    "DreamPolicy",
    "IMPORT",
    "MetaEvalCallback",
    "PRESETS",
    "RL2DQN",
    "VariBAD",
    "evaluate_meta",
    "__version__",
]
