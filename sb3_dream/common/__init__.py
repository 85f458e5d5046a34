"""Parts shared by the recurrent algorithms (RL2DQN, DREAM): the learn loop, embedders, sequence replay,
Q-learning helpers."""

from sb3_dream.common.buffers import SequenceReplayBuffer, SequenceReplayBufferSamples
from sb3_dream.common.embedders import (
    BoxMLPEmbedder,
    DiscreteEmbedder,
    ImageEmbedder,
    LinearEmbedder,
    MultiDiscreteEmbedder,
    TrialInputEmbedder,
    check_trial_observation_space,
    make_state_embedder,
)
from sb3_dream.common.off_policy import TrialOffPolicyAlgorithm
from sb3_dream.common.recurrent import (
    DuelingHead,
    LinearEpsilonSchedule,
    double_dqn_targets,
    masked_td_loss,
    reset_lstm_states,
    unroll_lstm,
    zero_lstm_states,
)
from sb3_dream.common.wrappers import FinalObsWrapper, RL2ObservationWrapper, final_obs_entry

__all__ = [
    "BoxMLPEmbedder",
    "DiscreteEmbedder",
    "DuelingHead",
    "FinalObsWrapper",
    "ImageEmbedder",
    "LinearEmbedder",
    "LinearEpsilonSchedule",
    "MultiDiscreteEmbedder",
    "RL2ObservationWrapper",
    "SequenceReplayBuffer",
    "SequenceReplayBufferSamples",
    "TrialInputEmbedder",
    "TrialOffPolicyAlgorithm",
    "check_trial_observation_space",
    "double_dqn_targets",
    "final_obs_entry",
    "make_state_embedder",
    "masked_td_loss",
    "reset_lstm_states",
    "unroll_lstm",
    "zero_lstm_states",
]
