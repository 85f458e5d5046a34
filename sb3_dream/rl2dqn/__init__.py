"""RL2DQN: the paper's RL² baseline, a recurrent dueling double DQN with sequence replay."""

from sb3_dream.rl2dqn.policies import CnnLstmPolicy, MultiInputLstmPolicy, RL2DQNPolicy, RL2QNetwork
from sb3_dream.rl2dqn.rl2dqn import RL2DQN, RL2TrialAgent, recurrent_double_dqn_loss

__all__ = [
    "CnnLstmPolicy",
    "MultiInputLstmPolicy",
    "RL2DQN",
    "RL2DQNPolicy",
    "RL2QNetwork",
    "RL2TrialAgent",
    "recurrent_double_dqn_loss",
]
