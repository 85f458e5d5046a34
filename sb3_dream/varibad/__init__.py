"""VariBAD: the paper's VariBAD baseline (Zintgraf et al., 2019) as a recurrent dueling double DQN
with reward and state decoders."""

from sb3_dream.varibad.policies import (
    CnnLstmPolicy,
    MultiInputLstmPolicy,
    TransitionDecoder,
    VariBADPolicy,
    VariBADQNetwork,
)
from sb3_dream.varibad.varibad import VariBAD, varibad_decoder_loss

__all__ = [
    "CnnLstmPolicy",
    "MultiInputLstmPolicy",
    "TransitionDecoder",
    "VariBAD",
    "VariBADPolicy",
    "VariBADQNetwork",
    "varibad_decoder_loss",
]
