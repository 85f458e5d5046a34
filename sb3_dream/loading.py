"""Load a saved model of any algorithm here without naming its class: :func:`load_model`.

SB3's ``save`` records the policy's class (with its module) in the zip's ``data``, not the
algorithm's; each algorithm of this package keeps its policies in its own package, so the
policy's module names the algorithm.
"""

from __future__ import annotations

import json
import zipfile
from typing import Any, Dict, Tuple

# The package holding an algorithm's policies -> (the algorithm's module, its class name).
ALGORITHM_OF_POLICY_PACKAGE: Dict[str, Tuple[str, str]] = {
    "sb3_dream.dream": ("sb3_dream.dream", "DREAM"),
    "sb3_dream.rl2dqn": ("sb3_dream.rl2dqn", "RL2DQN"),
    "sb3_dream.import_dqn": ("sb3_dream.import_dqn", "IMPORT"),
    "sb3_dream.varibad": ("sb3_dream.varibad", "VariBAD"),
}


def saved_algorithm(path: str) -> type:
    """The algorithm class of the model saved at ``path`` (DREAM, RL2DQN, IMPORT or VariBAD); a
    ValueError naming the accepted algorithms if the file holds another model."""
    import importlib

    with zipfile.ZipFile(path) as archive:
        data = json.loads(archive.read("data"))
    module = data.get("policy_class", {}).get("__module__", "")
    package = ".".join(module.split(".")[:2])
    if package not in ALGORITHM_OF_POLICY_PACKAGE:
        names = ", ".join(name for _, name in ALGORITHM_OF_POLICY_PACKAGE.values())
        raise ValueError(f"model={path!r} holds none of {names} (its policy is from {module or 'an unknown module'})")
    algo_module, name = ALGORITHM_OF_POLICY_PACKAGE[package]
    return getattr(importlib.import_module(algo_module), name)


def load_model(path: str, env: Any = None, device: str = "cpu", **kwargs: Any) -> Any:
    """The model saved at ``path``, loaded with its own algorithm's ``load`` (``env``, ``device``
    and ``kwargs`` as in SB3's ``load``)."""
    return saved_algorithm(path).load(path, env=env, device=device, **kwargs)


__all__ = ["ALGORITHM_OF_POLICY_PACKAGE", "load_model", "saved_algorithm"]
