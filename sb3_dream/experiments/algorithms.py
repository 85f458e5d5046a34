"""The algorithms the runner trains, one :class:`AlgorithmSpec` each, in the registry :data:`ALGORITHMS`.

A spec says how to build the algorithm's model from a :class:`~sb3_dream.experiments.config.RunConfig`
(its class, named presets and the command's overrides), what its name fixes, and the hooks the
runner calls around training. Adding an algorithm to the runner is registering its spec::

    register_algorithm(AlgorithmSpec("my_algo", load_class=lambda: MyAlgo, presets={"paper": {}},
                                     overrides="my_algo_kwargs"))

where ``overrides`` names the :class:`RunConfig` field (and ``--my-algo-kwargs`` flag) that holds
the command's constructor overrides. Parallel runs start fresh interpreters, so a spec registered
by a script must be registered when the script is imported, not only under ``__main__``.

A name can also fix env arguments (:attr:`AlgorithmSpec.env_kwargs`), for its training and
held-out evaluation envs alike. The paper's dashed lines (Figures 5 and 6: RL², IMPORT and VARIBAD
"with an instruction and rewards in the exploration episode") are such variants: each is its
algorithm trained and evaluated with ``reward_free_exploration=False``, named ``e_<name>``
(``e_rl2dqn`` is E-RL²), sharing the algorithm's class, presets and overrides, and drawn dashed in
its algorithm's colour. Registering one is one line, once its algorithm is registered::

    register_rewarded_exploration_variant("rl2dqn")  # e_rl2dqn

Registered here: ``dream``, ``dream_no_bottleneck``, ``rl2dqn``, ``import_dqn`` (IMPORT) and
``varibad`` (VARIBAD), and ``e_rl2dqn``, ``e_import_dqn``, ``e_varibad``.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import pathlib
from typing import TYPE_CHECKING, Any, Callable, Dict, Mapping, Optional, Tuple

from sb3_dream.presets import IMPORT_PRESETS, PRESETS, RL2DQN_PRESETS, VARIBAD_PRESETS, Preset

if TYPE_CHECKING:
    from sb3_dream.experiments.config import Run, RunConfig

# (model, the command's overrides, how many runs share the machine's cores) -> None
PrepareHook = Callable[[Any, Dict[str, Any], int], None]
# (final model, run, config, the run's log tag) -> entries added to the run's JSON record
ReportHook = Callable[[Any, "Run", "RunConfig", str], Dict[str, Any]]


@dataclasses.dataclass(frozen=True)
class AlgorithmSpec:
    """How the runner trains one algorithm, named ``name`` in ``--algos``.

    :param name: the runner's name of the algorithm (file names and ``--algos``)
    :param load_class: returns the SB3 algorithm class (imported on first use, so that
        importing the runner does not import torch)
    :param presets: the algorithm's named presets (:mod:`sb3_dream.presets`), chosen by ``--preset``
    :param overrides: the :class:`RunConfig` field holding the command's constructor overrides;
        several algorithms may share one (DREAM and its ablation share ``dream_kwargs``)
    :param fixed_kwargs: constructor arguments that the name fixes; the overrides may not set them
    :param prepare: called before each training session (fresh or going on from a checkpoint), to
        set how the model runs (not what it computes) for the overrides and the runs sharing the cores
    :param report: called on the final model; its entries are added to the run's JSON record
    :param env_kwargs: env constructor arguments that the name fixes, for the training and the
        evaluation envs (e.g. ``reward_free_exploration=False``); an env entry may not set them to
        other values
    :param variant_of: the registered algorithm this one is a variant of (figures draw both in one
        colour), or ``""``
    """

    name: str
    load_class: Callable[[], type]
    presets: Mapping[str, Preset]
    overrides: str
    fixed_kwargs: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    prepare: Optional[PrepareHook] = None
    report: Optional[ReportHook] = None
    env_kwargs: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    variant_of: str = ""

    @property
    def rewarded_exploration(self) -> bool:
        """Whether the name gives the exploration episode an instruction and rewards."""
        return self.env_kwargs.get("reward_free_exploration", True) is False


ALGORITHMS: Dict[str, AlgorithmSpec] = {}


def register_algorithm(spec: AlgorithmSpec) -> AlgorithmSpec:
    """Add ``spec`` to :data:`ALGORITHMS` (a ValueError if another spec has its name); returns it."""
    if ALGORITHMS.get(spec.name, spec) is not spec:
        raise ValueError(f"an algorithm named {spec.name!r} is already registered")
    ALGORITHMS[spec.name] = spec
    return spec


REWARDED_EXPLORATION_PREFIX = "e_"


def rewarded_exploration_variant(spec: AlgorithmSpec) -> AlgorithmSpec:
    """The paper's dashed-line variant of ``spec`` (E-RL² for RL²): named ``e_<name>``, trained and
    evaluated with an instruction and rewards in the exploration episode
    (``reward_free_exploration=False``); class, presets, overrides and hooks are ``spec``'s."""
    if spec.rewarded_exploration:
        raise ValueError(f"{spec.name} already explores with rewards")
    return dataclasses.replace(
        spec,
        name=REWARDED_EXPLORATION_PREFIX + spec.name,
        env_kwargs={**spec.env_kwargs, "reward_free_exploration": False},
        variant_of=spec.name,
    )


def register_rewarded_exploration_variant(algo: str) -> AlgorithmSpec:
    """Register (and return) :func:`rewarded_exploration_variant` of the registered ``algo``."""
    return register_algorithm(rewarded_exploration_variant(algorithm_spec(algo)))


def algorithm_env_kwargs(algo: str) -> Dict[str, Any]:
    """The env arguments that the name ``algo`` fixes (:attr:`AlgorithmSpec.env_kwargs`); none for
    a name not registered in this process (e.g. a finished run's record read by a report)."""
    spec = ALGORITHMS.get(algo)
    return dict(spec.env_kwargs) if spec is not None else {}


def algorithm_spec(algo: str) -> AlgorithmSpec:
    """The registered spec of ``algo``; a ValueError naming the registered ones otherwise."""
    try:
        return ALGORITHMS[algo]
    except KeyError:
        raise ValueError(f"algo={algo!r} is not valid; accepted values: {', '.join(map(repr, ALGORITHMS))}") from None


def preset_names() -> Tuple[str, ...]:
    """Every preset name that some registered algorithm defines."""
    return tuple(dict.fromkeys(name for spec in ALGORITHMS.values() for name in spec.presets))


def override_fields() -> Tuple[str, ...]:
    """The :class:`RunConfig` fields that hold the registered algorithms' overrides."""
    return tuple(dict.fromkeys(spec.overrides for spec in ALGORITHMS.values()))


def algorithm_class(algo: str) -> type:
    """The class that trains ``algo`` (DREAM for both DREAM variants)."""
    return algorithm_spec(algo).load_class()


def algorithm_kwargs(algo: str, config: "RunConfig") -> Dict[str, Any]:
    """The constructor arguments of ``algo`` that ``config`` sets: its preset, then its overrides."""
    spec = algorithm_spec(algo)
    if config.preset not in spec.presets:
        raise ValueError(
            f"preset={config.preset!r} is not defined for {algo}; its presets: {', '.join(map(repr, spec.presets))}"
        )
    return {**spec.presets[config.preset], **config.overrides(algo), **spec.fixed_kwargs}


def make_model(algo: str, env: Any, config: "RunConfig", seed: int) -> Any:
    """The model of ``algo`` on ``env`` with the preset and the per-algorithm overrides of ``config``."""
    return algorithm_class(algo)(env, seed=seed, device=config.device, **algorithm_kwargs(algo, config))


def load_with_overrides(algo: str, path: pathlib.Path, env: Any, config: "RunConfig") -> Any:
    """``algo``'s model saved at ``path``, with the hyperparameters that ``config`` sets to other
    values than the saved ones (set before the model is set up, as SB3's ``load(**kwargs)`` does).

    Only plain saved values (numbers, flags, strings) can change; the networks cannot.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    saved, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    wanted = algorithm_kwargs(algo, config)
    changed: Dict[str, Any] = {}
    for key, value in wanted.items():
        if key == "policy_kwargs":
            # The saved ones also hold what the algorithm derived from the env: compare the given keys.
            stored = saved.get(key) or {}
            given = {k: stored.get(k) for k in value}
            if json.dumps(value, default=str) != json.dumps(given, default=str):
                raise ValueError(f"policy_kwargs={value!r} differs from the checkpoint's {given!r}")
        elif key not in saved:
            # An option newer than the checkpoint: the checkpoint was made with its default.
            parameter = inspect.signature(algorithm_class(algo)).parameters.get(key)
            if parameter is None or parameter.default is inspect.Parameter.empty:
                raise ValueError(f"{key} cannot be changed when going on from a checkpoint")
            if parameter.default != value:
                changed[key] = value
        elif not isinstance(saved[key], (bool, int, float, str, type(None))):
            raise ValueError(f"{key} cannot be changed when going on from a checkpoint")
        elif saved[key] != value:
            changed[key] = value
    return algorithm_class(algo).load(path, env=env, device=config.device, **changed)


# ---------------------------------------------------------------------------------------------- DREAM
def _dream_class() -> type:
    from sb3_dream.dream import DREAM

    return DREAM


def _choose_parallel_updates(model: Any, overrides: Dict[str, Any], concurrent_runs: int) -> None:
    """DREAM's ``parallel_updates``, unless the command sets it: ``"auto"`` for a run alone, off
    when several runs share the cores. How the updates run, not what they compute (like the
    device), so chosen each session: a second thread only helps when no other run needs the core."""
    if "parallel_updates" not in overrides:
        model.parallel_updates = "auto" if concurrent_runs == 1 else False


def _evaluation_trials(run: "Run", config: "RunConfig") -> Dict[str, Any]:
    """The arguments of a diagnosis that plays the trials the run's held-out evaluation plays."""
    return {"n_trials": config.eval_trials, "env_kwargs": run.eval_kwargs, "exhaustive": config.eval_exhaustive}


def _diagnose_dream(model: Any, run: "Run", config: "RunConfig", tag: str) -> Dict[str, Any]:
    """The final model's :func:`sb3_dream.dream.diagnose` and :func:`sb3_dream.dream.exploration_gains`."""
    from sb3_dream.dream import diagnose

    # Which side limits the final model: meta-test vs the execution policy given z = f(T)
    # (and vs the decoder reading the env's optimal exploration).
    diagnosis = diagnose(model, run.env.env_id, **_evaluation_trials(run, config))
    # What its explorer is paid for, step by step (Equation 5), on the same trials.
    gains = diagnosis.exploration_gains
    print(
        f"[{tag}] diagnosis: {diagnosis.returns_text()}; "
        f"||g - f||^2 {diagnosis.decoder_error:.2f} vs spread of f {diagnosis.f_spread:.2f}",
        flush=True,
    )
    return {
        "diagnosis": diagnosis.as_dict(),
        "exploration_gains": {
            "reward_by_step": gains.by_step().tolist(),
            "information_gain": float(gains.information_gain().mean()),
            "reward_penalty": gains.reward_penalty,
        },
    }


def _dream_spec(name: str, bottleneck: bool) -> AlgorithmSpec:
    return AlgorithmSpec(
        name,
        load_class=_dream_class,
        presets=PRESETS,
        overrides="dream_kwargs",
        fixed_kwargs={"bottleneck": bottleneck},
        prepare=_choose_parallel_updates,
        report=_diagnose_dream,
    )


def _rl2dqn_class() -> type:
    from sb3_dream.rl2dqn import RL2DQN

    return RL2DQN


def _import_class() -> type:
    from sb3_dream.import_dqn import IMPORT

    return IMPORT


def _diagnose_import(model: Any, run: "Run", config: "RunConfig", tag: str) -> Dict[str, Any]:
    """The final model's :func:`sb3_dream.import_dqn.diagnose`: its return with z = e(T) beside
    meta-test's, and how far e(tau_:t) stays from e(T)."""
    from sb3_dream.import_dqn import diagnose

    diagnosis = diagnose(model, run.env.env_id, **_evaluation_trials(run, config))
    print(f"[{tag}] diagnosis: {diagnosis.text()}", flush=True)
    return {"diagnosis": diagnosis.as_dict()}


def _varibad_class() -> type:
    from sb3_dream.varibad import VariBAD

    return VariBAD


register_algorithm(_dream_spec("dream", bottleneck=True))
register_algorithm(_dream_spec("dream_no_bottleneck", bottleneck=False))  # the paper's ablation
register_algorithm(AlgorithmSpec("rl2dqn", _rl2dqn_class, RL2DQN_PRESETS, "rl2dqn_kwargs"))  # the RL² baseline
register_rewarded_exploration_variant("rl2dqn")  # e_rl2dqn: E-RL², the paper's dashed RL² line
register_algorithm(  # the IMPORT baseline
    AlgorithmSpec("import_dqn", _import_class, IMPORT_PRESETS, "import_kwargs", report=_diagnose_import)
)
register_rewarded_exploration_variant("import_dqn")  # e_import_dqn: the paper's dashed IMPORT line
register_algorithm(AlgorithmSpec("varibad", _varibad_class, VARIBAD_PRESETS, "varibad_kwargs"))  # the VARIBAD baseline
register_rewarded_exploration_variant("varibad")  # e_varibad: the paper's dashed VARIBAD line
