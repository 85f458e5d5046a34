from sb3_dream.dream.diagnostics import (
    DreamDiagnosis,
    ExplorationGains,
    PrivilegedAgent,
    PrivilegedBatchAgent,
    diagnose,
    exploration_gains,
    f_variance_by_feature,
)
from sb3_dream.dream.dream import DREAM
from sb3_dream.dream.policies import DreamPolicy
from sb3_dream.evaluation import trial_problem_ids  # where it lives; kept importable from here

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
