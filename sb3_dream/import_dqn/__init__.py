"""IMPORT: the paper's IMPORT baseline (Kamienny et al., 2020), a recurrent dueling double DQN
whose Q reads the problem embedding or the history embedding, alternating per trial."""

from sb3_dream.import_dqn.import_dqn import (
    IMPORT,
    ProblemSequenceReplayBuffer,
    ProblemSequenceSamples,
    import_aux_loss,
)
from sb3_dream.import_dqn.diagnostics import IMPORTDiagnosis, ProblemCodeBatchAgent, diagnose
from sb3_dream.import_dqn.policies import CnnLstmPolicy, IMPORTPolicy, IMPORTQNetwork, MultiInputLstmPolicy

__all__ = [
    "CnnLstmPolicy",
    "IMPORT",
    "IMPORTDiagnosis",
    "IMPORTPolicy",
    "IMPORTQNetwork",
    "MultiInputLstmPolicy",
    "ProblemCodeBatchAgent",
    "ProblemSequenceReplayBuffer",
    "ProblemSequenceSamples",
    "diagnose",
    "import_aux_loss",
]
