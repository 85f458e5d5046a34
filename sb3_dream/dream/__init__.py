from sb3_dream.dream.diagnostics import DreamDiagnosis, diagnose
from sb3_dream.dream.dream import DREAM
from sb3_dream.dream.policies import DreamPolicy

__all__ = ["DREAM", "DreamDiagnosis", "DreamPolicy", "diagnose"]
