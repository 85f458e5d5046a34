"""The experiment runner: algorithms x envs x seeds -> learning curves, a summary table and figures.

``python -m sb3_dream.experiments --help`` describes the command (:mod:`sb3_dream.experiments.cli`).
The package, by concept:

* :mod:`~sb3_dream.experiments.config`: env specs, the settings shared by the runs, each run's files;
* :mod:`~sb3_dream.experiments.algorithms`: the algorithms the runner trains, one spec each;
* :mod:`~sb3_dream.experiments.training`: one run (train, evaluate, record);
* :mod:`~sb3_dream.experiments.checkpoints`: resuming, extending and starting from other runs;
* :mod:`~sb3_dream.experiments.backends`: where runs execute (:class:`LocalPool`: processes here);
* :mod:`~sb3_dream.experiments.ray_backend`: :class:`RayBackend`, the runs as Ray tasks (``[ray]`` extra);
* :mod:`~sb3_dream.experiments.runner`: which runs are due, handed to a backend;
* :mod:`~sb3_dream.experiments.lock`: one runner at a time per experiment folder;
* :mod:`~sb3_dream.experiments.report`: summaries, the oracle's return, the figure.
"""

from sb3_dream.experiments.algorithms import (
    ALGORITHMS,
    AlgorithmSpec,
    algorithm_class,
    algorithm_kwargs,
    load_with_overrides,
    make_model,
    register_algorithm,
    register_rewarded_exploration_variant,
    rewarded_exploration_variant,
)
from sb3_dream.experiments.backends import Backend, LocalPool
from sb3_dream.experiments.checkpoints import Checkpointer, init_checkpoint
from sb3_dream.experiments.cli import build_parser, main
from sb3_dream.experiments.config import EnvSpec, Run, RunConfig, parse_kwargs
from sb3_dream.experiments.lock import FolderLocked, runner_lock
from sb3_dream.experiments.ray_backend import RayBackend, RayUnavailable
from sb3_dream.experiments.report import (
    SUMMARY_COLUMNS,
    finished_runs,
    load_curve,
    oracle_return,
    parse_folder_spec,
    pearl_ub_return,
    plot_curves,
    report_folders,
    summarize,
    write_summary,
)
from sb3_dream.experiments.runner import check_eval_splits, check_presets, plan_runs, run_experiments
from sb3_dream.experiments.training import run_one

__all__ = [
    "ALGORITHMS",
    "AlgorithmSpec",
    "Backend",
    "Checkpointer",
    "EnvSpec",
    "FolderLocked",
    "LocalPool",
    "RayBackend",
    "RayUnavailable",
    "Run",
    "RunConfig",
    "SUMMARY_COLUMNS",
    "algorithm_class",
    "algorithm_kwargs",
    "build_parser",
    "check_eval_splits",
    "check_presets",
    "finished_runs",
    "init_checkpoint",
    "load_curve",
    "load_with_overrides",
    "main",
    "make_model",
    "oracle_return",
    "parse_folder_spec",
    "parse_kwargs",
    "pearl_ub_return",
    "plan_runs",
    "plot_curves",
    "register_algorithm",
    "register_rewarded_exploration_variant",
    "report_folders",
    "rewarded_exploration_variant",
    "run_experiments",
    "run_one",
    "runner_lock",
    "summarize",
    "write_summary",
]
