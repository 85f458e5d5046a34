"""rl-zoo3 integration: train, tune and watch DREAM, RL2DQN, IMPORT and VariBAD with the RL Baselines3 Zoo.

rl-zoo3 has no plugin mechanism: its algorithms live in the dict ``rl_zoo3.utils.ALGOS`` (also
exported as ``rl_zoo3.ALGOS``) and its Optuna samplers in
``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER`` (with ``HYPERPARAMS_CONVERTER``, which turns a
stored trial's parameters back into constructor arguments). :func:`register` adds to all three:

==============  ======================================  ==========================================
zoo name        algorithm                               default hyperparameter file
==============  ======================================  ==========================================
``dream``       :class:`sb3_dream.DREAM`                ``sb3_dream/zoo/hyperparams/dream.yml``
``rl2_dqn``     :class:`sb3_dream.rl2dqn.RL2DQN`        ``sb3_dream/zoo/hyperparams/rl2_dqn.yml``
``import_dqn``  :class:`sb3_dream.import_dqn.IMPORT`    ``sb3_dream/zoo/hyperparams/import_dqn.yml``
``varibad``     :class:`sb3_dream.varibad.VariBAD`      ``sb3_dream/zoo/hyperparams/varibad.yml``
==============  ======================================  ==========================================

Each also ships ``<name>_measured.yml`` (``sb3-dream-zoo train ... --settings measured``): the
settings of the README's measured runs (:data:`MEASURED_ALGOS`; their results:
``docs/results/README.md`` and, for the baselines, ``docs/baselines.md``): the ``fast`` schedules
and 4 envs, with DREAM's options of each env's best runs.

The ``sb3-dream-zoo`` command (:mod:`sb3_dream.zoo.cli`) registers them, imports
:mod:`dream_envs` (so ``--env MetaBus-v0`` resolves) and runs rl-zoo3's own ``train``,
``enjoy`` or ``record_video`` with every flag passed through::

    sb3-dream-zoo train --algo dream --env MetaBus-v0 --env-kwargs variant:"'map'"
    sb3-dream-zoo enjoy --algo dream --env MetaBus-v0 -n 400

From Python (e.g. a script that calls rl-zoo3's functions itself)::

    import sb3_dream.zoo
    sb3_dream.zoo.register()
"""

from __future__ import annotations

import pathlib
from typing import Dict, Type

from stable_baselines3.common.base_class import BaseAlgorithm

from dream_envs.checks import check_choice

HYPERPARAMS_DIR = pathlib.Path(__file__).resolve().parent / "hyperparams"
ZOO_ALGOS = ("dream", "rl2_dqn", "import_dqn", "varibad")
MEASURED_ALGOS = ZOO_ALGOS  # the algorithms with a "measured" file (the README's runs)
LAPTOP_ALGOS = ("dream",)  # the algorithms with a "laptop" file (sb3_dream.PRESETS["laptop"])
#: the packaged hyperparameter files: each setting and the algorithms that have it
SETTINGS_ALGOS = {"paper": ZOO_ALGOS, "measured": MEASURED_ALGOS, "laptop": LAPTOP_ALGOS}
SETTINGS = tuple(SETTINGS_ALGOS)


def algorithms() -> Dict[str, Type[BaseAlgorithm]]:
    """The zoo names and classes of this package's algorithms."""
    from sb3_dream.dream import DREAM
    from sb3_dream.import_dqn import IMPORT
    from sb3_dream.rl2dqn import RL2DQN
    from sb3_dream.varibad import VariBAD

    return {"dream": DREAM, "rl2_dqn": RL2DQN, "import_dqn": IMPORT, "varibad": VariBAD}


def hyperparams_path(algo: str, settings: str = "paper") -> pathlib.Path:
    """The packaged hyperparameter file of ``algo`` (one of :data:`ZOO_ALGOS`), usable as ``--conf-file``.

    ``settings="paper"``: the paper's values (the constructors' defaults); ``"measured"``: the
    settings of the README's measured runs (the ``fast`` schedules and DREAM's options), for the
    algorithms of :data:`MEASURED_ALGOS`; ``"laptop"``: DREAM's ``PRESETS["laptop"]`` (the
    Quickstart's settings), for the algorithms of :data:`LAPTOP_ALGOS`.
    """
    check_choice("algo", algo, ZOO_ALGOS)
    having = SETTINGS_ALGOS[check_choice("settings", settings, SETTINGS)]
    if algo not in having:
        raise ValueError(
            f"algo={algo!r} has no {settings!r} settings (algorithms with them: {', '.join(map(repr, having))}); "
            "use settings='paper'"
        )
    return HYPERPARAMS_DIR / (f"{algo}.yml" if settings == "paper" else f"{algo}_{settings}.yml")


def register() -> None:
    """Add this package's algorithms (:data:`ZOO_ALGOS`) to rl-zoo3's algorithm table and Optuna samplers (idempotent);
    ``--optimize`` then reports the held-out meta-test return of trial envs to Optuna
    (:func:`sb3_dream.zoo.hyperparams_opt.meta_test_trial_eval_callback`).

    Also imports :mod:`dream_envs`, which registers the trial envs with Gymnasium.

    :raises ImportError: if rl-zoo3 is not installed (``pip install "sb3-dream[zoo]"``).
    """
    try:
        import rl_zoo3.hyperparams_opt as zoo_opt
        import rl_zoo3.utils as zoo_utils
    except ImportError as error:
        raise ImportError(
            'sb3_dream.zoo needs rl-zoo3: pip install "sb3-dream[zoo]" (or pip install rl_zoo3)'
        ) from error

    import rl_zoo3.exp_manager as zoo_exp_manager

    import dream_envs  # noqa: F401  (registers MetaBus-v0, MetaCook-v0, SignNav3D-v0, MetaBandit-v0)
    from sb3_dream.zoo.hyperparams_opt import CONVERTERS, SAMPLERS, meta_test_trial_eval_callback

    # Mutate the tables in place: train.py, enjoy.py and exp_manager.py all imported these same
    # dict objects, so the names become valid --algo choices everywhere.
    zoo_utils.ALGOS.update(algorithms())
    zoo_opt.HYPERPARAMS_SAMPLER.update(SAMPLERS)
    if hasattr(zoo_opt, "HYPERPARAMS_CONVERTER"):  # absent from older rl-zoo3 releases
        zoo_opt.HYPERPARAMS_CONVERTER.update(CONVERTERS)
    # --optimize reports (and prunes on) the held-out meta-test return of trial envs.
    if not getattr(zoo_exp_manager.TrialEvalCallback, "meta_test", False):
        callback = meta_test_trial_eval_callback()
        callback.meta_test = True
        zoo_exp_manager.TrialEvalCallback = callback


__all__ = [
    "HYPERPARAMS_DIR",
    "LAPTOP_ALGOS",
    "MEASURED_ALGOS",
    "SETTINGS",
    "SETTINGS_ALGOS",
    "ZOO_ALGOS",
    "algorithms",
    "hyperparams_path",
    "register",
]
