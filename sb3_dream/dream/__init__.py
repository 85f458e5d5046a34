from sb3_dream.dream.diagnostics import (
    DreamDiagnosis,
    ExplorationGains,
    PrivilegedAgent,
    PrivilegedBatchAgent,
    diagnose,
    exploration_gains,
    f_variance_by_feature,
    trial_problem_ids,
)
from sb3_dream.dream.dream import DREAM
from sb3_dream.dream.policies import DreamPolicy

__all__ = [
    "DREAM",
    "DreamDiagnosis",
    "DreamPolicy",
    "ExplorationGains",
    "PrivilegedAgent",
    "PrivilegedBatchAgent",
    "diagnose",
    "exploration_gains",
    "f_variance_by_feature",
    "trial_problem_ids",
]
