from sb3_dream.dream.diagnostics import (
    DreamDiagnosis,
    PrivilegedAgent,
    PrivilegedBatchAgent,
    diagnose,
    f_variance_by_feature,
    trial_problem_ids,
)
from sb3_dream.dream.dream import DREAM
from sb3_dream.dream.policies import DreamPolicy

__all__ = [
    "DREAM",
    "DreamDiagnosis",
    "DreamPolicy",
    "PrivilegedAgent",
    "PrivilegedBatchAgent",
    "diagnose",
    "f_variance_by_feature",
    "trial_problem_ids",
]
