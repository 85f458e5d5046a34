"""What an experiment runs: env specs, the settings shared by its runs, and each run's files."""

from __future__ import annotations

import ast
import dataclasses
import pathlib
from typing import Any, Dict, Sequence, Tuple

from dream_envs import all_splits
from dream_envs.checks import check_choice
from sb3_dream.evaluation import BEST_TIES
from sb3_dream.experiments.algorithms import (
    ALGORITHMS,
    algorithm_env_kwargs,
    algorithm_spec,
    override_fields,
    preset_names,
)


def _parse_value(text: str) -> Any:
    """A Python literal if ``text`` is one (``3``, ``0.5``, ``True``, ``'map'``), else the string."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_kwargs(items: Sequence[str], name: str) -> Dict[str, Any]:
    """``["a=1", "b=map"]`` -> ``{"a": 1, "b": "map"}``; a ValueError naming ``name`` otherwise."""
    kwargs: Dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"{name} entries must look like key=value, got {item!r}")
        kwargs[key] = _parse_value(value)
    return kwargs


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """A registered env ID and constructor arguments: ``"MetaBus-v0:variant=map:n_exec_episodes=2"``.

    Colon-separated parts with ``=`` are arguments; the others form the ID, so the
    ``"dream_envs:MetaBus-v0"`` form also works.
    """

    env_id: str
    kwargs: Tuple[Tuple[str, Any], ...] = ()

    @classmethod
    def parse(cls, text: str) -> "EnvSpec":
        parts = text.split(":")
        id_parts = [p for p in parts if "=" not in p]
        if not id_parts or not all(id_parts):
            raise ValueError(
                f"envs entry {text!r} is not valid: expected ENV_ID[:key=value...], e.g. MetaBus-v0:variant=map"
            )
        kwargs = parse_kwargs([p for p in parts if "=" in p], f"envs entry {text!r}")
        return cls(":".join(id_parts), tuple(sorted(kwargs.items())))

    @property
    def env_kwargs(self) -> Dict[str, Any]:
        """Arguments of the training env (all of them)."""
        return dict(self.kwargs)

    @property
    def eval_kwargs(self) -> Dict[str, Any]:
        """Arguments of the evaluation env (``split`` and ``n_exec_episodes`` are set separately)."""
        return {k: v for k, v in self.kwargs if k not in ("split", "n_exec_episodes")}

    @property
    def n_exec_episodes(self) -> int:
        return int(self.env_kwargs.get("n_exec_episodes", 1))

    @property
    def tag(self) -> str:
        """A folder name: ``MetaBus-v0_variant-map``."""
        name = self.env_id.split(":")[-1]
        return "_".join([name, *(f"{k}-{v}" for k, v in self.kwargs)]).replace("/", "-").replace(" ", "")

    @property
    def label(self) -> str:
        """A title: ``MetaBus-v0 (variant=map)``."""
        name = self.env_id.split(":")[-1]
        return name + (" (" + ", ".join(f"{k}={v}" for k, v in self.kwargs) + ")" if self.kwargs else "")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Settings shared by every run of an experiment."""

    steps: int = 100_000
    n_envs: int = 1
    preset: str = "paper"
    eval_freq: int = 10_000
    eval_trials: int = 100
    eval_splits: Tuple[str, ...] = ("test",)
    eval_exhaustive: bool = False
    threads: int = 1
    device: str = "auto"
    save_models: bool = False
    checkpoint_freq: int = 0
    snapshot_freq: int = 0
    tensorboard: bool = False
    select_on: str = ""
    select_ties: str = "last"
    # Constructor overrides, sorted (key, value) pairs, one field per AlgorithmSpec.overrides.
    dream_kwargs: Tuple[Tuple[str, Any], ...] = ()
    rl2dqn_kwargs: Tuple[Tuple[str, Any], ...] = ()
    import_kwargs: Tuple[Tuple[str, Any], ...] = ()
    varibad_kwargs: Tuple[Tuple[str, Any], ...] = ()
    init_from: str = ""

    def __post_init__(self) -> None:
        for name in ("steps", "n_envs", "eval_freq", "eval_trials", "threads"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.preset not in preset_names():
            raise ValueError(
                f"preset={self.preset!r} is not valid; accepted values: {', '.join(map(repr, preset_names()))}"
            )
        known = all_splits()
        if not self.eval_splits or any(s not in known for s in self.eval_splits):
            raise ValueError(
                f"eval_splits={self.eval_splits!r} is not valid; accepted values: {', '.join(map(repr, known))}"
            )
        for name in ("checkpoint_freq", "snapshot_freq"):
            freq = getattr(self, name)
            if isinstance(freq, bool) or not isinstance(freq, int) or freq < 0:
                raise ValueError(f"{name} must be an integer >= 0 (0: off), got {freq!r}")
        if self.select_on and self.select_on not in self.eval_splits:
            raise ValueError(
                f"select_on={self.select_on!r} is not valid; accepted values: the evaluated splits "
                f"{', '.join(map(repr, self.eval_splits))} (add it to eval_splits), or '' (off)"
            )
        check_choice("select_ties", self.select_ties, BEST_TIES)
        for spec in ALGORITHMS.values():
            fixed = sorted(set(spec.fixed_kwargs) & set(self.overrides(spec.name)))
            if fixed:
                # the algorithms that fix these arguments, one way or the other
                sharing = [
                    other.name
                    for other in ALGORITHMS.values()
                    if other.overrides == spec.overrides and set(fixed) <= set(other.fixed_kwargs)
                ]
                raise ValueError(
                    f"{spec.overrides} must not set {', '.join(fixed)}: choose the algorithm {' or '.join(sharing)}"
                )

    def overrides(self, algo: str) -> Dict[str, Any]:
        """The constructor overrides that this config gives ``algo`` (its spec's field)."""
        return dict(getattr(self, algorithm_spec(algo).overrides))

    def settings(self, algo: str) -> Dict[str, Any]:
        """What a finished run of ``algo`` records, to warn when a later command asks for other settings."""
        data = dataclasses.asdict(self)
        unrecorded = ("threads", "device", "save_models", "checkpoint_freq", "snapshot_freq", "tensorboard")
        unrecorded += ("select_on", "select_ties")  # which model is kept, not how it trains
        for key in (*unrecorded, *override_fields()):
            data.pop(key)
        data["algo_kwargs"] = self.overrides(algo)
        data["eval_splits"] = list(self.eval_splits)
        for key in ("init_from", "eval_exhaustive"):
            if not data[key]:
                data.pop(key)  # records made before the option compare equal
        return data


def split_suffix(split: str) -> str:
    """What names a split's curve and logger keys: nothing for the held-out split (``test``), the
    curve ``<run>.csv`` and SB3's ``eval/``; ``_<split>`` for the others (``<run>_train.csv``, ``eval_train/``)."""
    return "" if split == "test" else f"_{split}"


@dataclasses.dataclass(frozen=True)
class Run:
    """One (algorithm, env, seed) run and where its files go."""

    algo: str
    env: EnvSpec
    seed: int

    @property
    def name(self) -> str:
        return f"{self.algo}_seed{self.seed}"

    @property
    def env_kwargs(self) -> Dict[str, Any]:
        """Arguments of the run's training env: the env entry's, and those the algorithm's name
        fixes (:attr:`~sb3_dream.experiments.algorithms.AlgorithmSpec.env_kwargs`, e.g. E-RL²'s
        ``reward_free_exploration=False``)."""
        return {**self.env.env_kwargs, **algorithm_env_kwargs(self.algo)}

    @property
    def eval_kwargs(self) -> Dict[str, Any]:
        """Arguments of the run's evaluation envs (``split`` and ``n_exec_episodes`` are set
        separately): the env entry's and those the algorithm's name fixes."""
        return {**self.env.eval_kwargs, **algorithm_env_kwargs(self.algo)}

    def check_env_kwargs(self) -> None:
        """Raise a ``ValueError`` if the env entry sets an argument that the algorithm's name fixes
        to another value."""
        for key, value in algorithm_env_kwargs(self.algo).items():
            if key in self.env.env_kwargs and self.env.env_kwargs[key] != value:
                raise ValueError(
                    f"{self.env.label} sets {key}={self.env.env_kwargs[key]!r}, but {self.algo} runs with "
                    f"{key}={value!r}: drop it from the env entry, or choose another algorithm"
                )

    def folder(self, out: pathlib.Path) -> pathlib.Path:
        return out / self.env.tag

    def curve_path(self, out: pathlib.Path, split: str = "test") -> pathlib.Path:
        return self.folder(out) / f"{self.name}{split_suffix(split)}.csv"

    def info_path(self, out: pathlib.Path) -> pathlib.Path:
        return self.folder(out) / f"{self.name}.json"

    def model_path(self, out: pathlib.Path) -> pathlib.Path:
        return self.folder(out) / f"{self.name}.zip"

    def best_folder(self, out: pathlib.Path) -> pathlib.Path:
        """Where ``--select-on`` keeps the run's best model (``best_model.zip``)."""
        return self.folder(out) / "best" / self.name

    def tensorboard_folder(self, out: pathlib.Path) -> pathlib.Path:
        """The ``tensorboard_log`` of the run's model with ``--tensorboard``: its log is ``<name>_1`` in it."""
        return self.folder(out) / "tensorboard"

    def checkpoint_path(self, out: pathlib.Path) -> pathlib.Path:
        """The JSON that names a run's last checkpoint (written last, so it is never half made)."""
        return self.folder(out) / "checkpoints" / f"{self.name}.json"

    def is_complete(self, out: pathlib.Path, config: RunConfig) -> bool:
        return all(self.curve_path(out, split).exists() for split in config.eval_splits)
