"""Named hyperparameter sets, the one source of presets: ``DREAM(env, **PRESETS["fast"])``.

:data:`PRESETS` holds DREAM's, :data:`RL2DQN_PRESETS` RL2DQN's (:data:`IMPORT_PRESETS`,
:data:`VARIBAD_PRESETS` the other baselines'), under the same names; the
experiment runner (``--preset``) and the rl-zoo3 hyperparameter files read them from here (a test
checks the zoo's YAML files agree). Each preset is a dict of constructor keyword arguments.

``paper`` is the default (Appendix B.4 and Table 1; learning starts from the authors' code).
``fast`` changes only *when and how long* things happen, for the grid worlds on a laptop CPU;
every network, loss and the update ratio (one update of each part per 4 env steps)
stay the paper's:

* ``exploration_learning_starts`` 8000 -> 100 trials and ``execution_learning_starts`` 500 -> 100:
  the paper waits 8000 trials before the exploration policy learns at all;
* ``eps_decay_steps`` 250K -> 30K per policy: epsilon-greedy reaches 0.01 after 30K steps of each;
* ``target_update_interval`` 5000 -> 1000 updates: targets follow faster on small problems.

RL2DQN's ``fast`` makes the same schedule changes in its own terms: learning starts after about
100 trials of the grid worlds (4000 env steps instead of 16000), epsilon decays over 60K steps
(DREAM's 2 x 30K) instead of 500K, and targets sync every 1000 updates instead of 5000.

:data:`IMPORT_PRESETS` and :data:`VARIBAD_PRESETS` are RL2DQN's: the baselines share its
hyperparameters in the paper (Table 1) and its ``fast`` schedules here.

Compared side by side by ``benchmarks/learning_curves.py --preset paper|fast`` (see docs/results/metabus.md).

``laptop`` is ``fast`` plus the options that shortened the wall-clock to a solved MetaBus map on a
2-core CPU (docs/speed.md, "Time to solve"; the Quickstart's settings):

* ``policy_kwargs=dict(execution_hidden_sizes=(128, 128), execution_recurrent=True)``: a wider
  execution body (the paper's one layer of 64 plateaus below the optimum on the map) with an LSTM
  over each execution episode, as in the authors' final code;
* ``execution_sampling="episodes"``: an execution update learns from 32 whole execution episodes
  (what the recurrent network needs) instead of Algorithm 1's 32 transitions.

It is a DREAM preset only (the baselines have none), and its ``policy_kwargs`` is a dict: to change
another policy argument, merge it, ``{**PRESETS["laptop"]["policy_kwargs"], "z_dim": 32}``.
"""

from typing import Any, Dict

Preset = Dict[str, Any]

PRESETS: Dict[str, Preset] = {
    "paper": {},
    "fast": {
        "exploration_learning_starts": 100,
        "execution_learning_starts": 100,
        "eps_decay_steps": 30_000,
        "target_update_interval": 1000,
    },
}
PRESETS["laptop"] = {
    **PRESETS["fast"],
    "policy_kwargs": {"execution_hidden_sizes": (128, 128), "execution_recurrent": True},
    "execution_sampling": "episodes",
}

RL2DQN_PRESETS: Dict[str, Preset] = {
    "paper": {},
    "fast": {"learning_starts": 4000, "exploration_steps": 60_000, "target_update_interval": 1000},
}

# IMPORT and VariBAD share RL²'s hyperparameters (the paper's Table 1) and so its schedules.
IMPORT_PRESETS: Dict[str, Preset] = {"paper": {}, "fast": dict(RL2DQN_PRESETS["fast"])}

VARIBAD_PRESETS: Dict[str, Preset] = {"paper": {}, "fast": dict(RL2DQN_PRESETS["fast"])}

__all__ = ["IMPORT_PRESETS", "PRESETS", "Preset", "RL2DQN_PRESETS", "VARIBAD_PRESETS"]
