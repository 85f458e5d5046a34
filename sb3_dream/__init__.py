"""sb3-dream: DREAM and RL² for Stable-Baselines3."""

import dream_envs  # noqa: F401  (registers the meta-RL envs so env IDs resolve)
from sb3_dream.dream import DREAM, DreamPolicy
from sb3_dream.evaluation import MetaEvalCallback, evaluate_meta
from sb3_dream.presets import PRESETS
from sb3_dream.rl2dqn import RL2DQN
from sb3_dream.version import __version__

__all__ = ["DREAM", "DreamPolicy", "MetaEvalCallback", "PRESETS", "RL2DQN", "evaluate_meta", "__version__"]
