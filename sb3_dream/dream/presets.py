"""Named hyperparameter sets for DREAM: ``DREAM(env, **PRESETS["fast"])``.

``paper`` is the default (Appendix B.4 and Table 1; learning starts from the authors' code).
``fast`` changes only *when and how long* things happen, to learn the grid worlds in minutes on a
laptop CPU; every network, loss and the update ratio (one update of each part per 4 env steps)
stay the paper's:

* ``exploration_learning_starts`` 8000 -> 100 trials and ``execution_learning_starts`` 500 -> 100:
  the paper waits 8000 trials (~250K steps) before the exploration policy learns at all;
* ``eps_decay_steps`` 250K -> 30K per policy: epsilon-greedy reaches 0.01 after 30K steps of each;
* ``target_update_interval`` 5000 -> 1000 updates: targets follow faster on small problems.

Measured side by side by ``benchmarks/learning_curves.py --preset paper|fast`` (see docs/results.md).
"""

from typing import Any, Dict

PRESETS: Dict[str, Dict[str, Any]] = {
    "paper": {},
    "fast": {
        "exploration_learning_starts": 100,
        "execution_learning_starts": 100,
        "eps_decay_steps": 30_000,
        "target_update_interval": 1000,
    },
}
