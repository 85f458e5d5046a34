"""Experiment runner: algorithms x envs x seeds -> learning curves, a summary table and figures.

Each run trains one algorithm on one env with one seed for ``--steps`` env steps and evaluates it
on the held-out split every ``--eval-freq`` steps (``--eval-trials`` meta-test trials, greedy; with
``--eval-exhaustive`` every (problem, instruction) pair of the split, weighted) with
:class:`sb3_dream.evaluation.MetaEvalCallback`, which writes the run's learning curve as a CSV
(``env_steps, wall_clock_s, mean, ci, exploration_length``). Runs go to parallel processes, up to
``--jobs`` (default: the machine's cores) at once. DREAM's ``parallel_updates`` (the second update
thread) is chosen per run unless ``--dream-kwargs`` set it: its ``"auto"`` for a run alone, off
when several runs share the cores (it changes the speed, not the results).

**Resumable.** A run writes ``<name>.csv.partial`` and renames it to ``<name>.csv`` only when it
is complete, so a finished run is skipped when the command is run again (whatever the other
options: use ``--force`` or a new ``--out`` to redo it). An interrupted run starts over, unless
``--checkpoint-freq N`` is given: then, right after an evaluation and at least every N env steps,
the run saves its model (with optimizer states and counters) and replay buffers under
``<env>/checkpoints/``, and the same command later goes on from the last checkpoint, keeping the
learning curve and wall-clock so far (the envs start fresh trials; nothing else is lost). This is
how budgets longer than one sitting (the paper's millions of steps) are run on a laptop. Its
worker processes end with the runner however it is stopped (Ctrl-C, ``kill``, ``kill -9``), so
none trains on unseen into ``--out``.
A complete run keeps its last checkpoint (at its final step), so the same command with a larger
``--steps`` later *extends* it from there instead of skipping it; ``--force`` deletes it and
starts over. Delete ``<env>/checkpoints/`` to free the space once no run needs extending.

**One runner per folder.** A runner holds ``<out>/.runner.lock`` while it trains (released when
it ends, however it ends); a second runner on the same ``--out`` stops at once with an error
naming the first (pid, host, start time, command line). A lock record left by a killed runner is
taken over, with a note on stderr. ``--summary-only`` only reads the runs and needs no lock; the
summary files and the figure are replaced atomically.

**Going on with other settings.** ``--init-from DIR`` starts each run that has no checkpoint of its
own from the kept final checkpoint of the same run (algorithm, env, seed) under ``DIR``, with this
command's preset and overrides applied to the loaded model (SB3's ``load(**kwargs)``; the networks,
``policy_kwargs`` included, must stay the same). Its learning curve and wall-clock carry over, so
the new run's curve starts where the parent's ended: e.g. a run made to 1M steps with one target
sync interval goes on to 1.2M with another, into its own ``--out``. The run's JSON records the
parent (``init_from``: its ``--out`` and env steps), also once the run is resumed or extended from
its own checkpoints.

**On a Ray cluster.** ``--backend ray`` runs each run as a Ray task
(:mod:`~sb3_dream.experiments.ray_backend`; ``pip install "sb3-dream[ray]"``): on the cluster at
``--ray-address HOST:PORT`` (``ray start --head`` prints it) or, without it, on a Ray started on
this machine for the experiment. Each run reserves ``--cpus-per-run`` CPUs (default ``--threads``)
and ``--gpus-per-run`` GPUs; a run whose worker dies is rerun up to ``--max-retries`` times, from
its last checkpoint with ``--checkpoint-freq``. The tasks write into ``--out``, which must be on a
filesystem that every node mounts at the same path.

**Outputs** under ``--out``::

    <env>/<algo>_seed<k>.csv          learning curve on the held-out split (--eval-splits test)
    <env>/<algo>_seed<k>_train.csv    ... on the training split, with --eval-splits test train
                                      (likewise _<split>.csv for any split the env offers, e.g.
                                      MetaCook's test_problems and test_instructions)
    <env>/<algo>_seed<k>.json         the run's settings and final numbers (DREAM: also the final
                                      model's :func:`sb3_dream.dream.diagnose` and
                                      :func:`sb3_dream.dream.exploration_gains`)
    <env>/<algo>_seed<k>.zip          the trained model, with --save-models
    <env>/oracle_<split>.json         the env's scripted optimal agent on that split (oracle_<split>_exhaustive.json
                                      with --eval-exhaustive)
    <env>/checkpoints/                each run's last checkpoint, with --checkpoint-freq
    <env>/snapshots/                  the model every N env steps, with --snapshot-freq N (SB3's
                                      CheckpointCallback: <algo>_seed<k>_<steps>_steps.zip, no
                                      replay buffers), to meta-test how a policy changes
    <env>/tensorboard/<algo>_seed<k>_1/
                                      with --tensorboard: SB3's TensorBoard log of the run (rollout/
                                      and train/ keys, the held-out evaluations as eval/, the
                                      training split's as eval_train/; a resumed run goes on in it)
    <env>/best/<algo>_seed<k>/best_model.zip
                                      with --select-on SPLIT: the model at the evaluation on SPLIT
                                      with the highest return so far, the latest of equal ones
                                      (--select-ties; MetaEvalCallback's best_model_save_path); the
                                      run's JSON records its steps and its return on the held-out
                                      split ("best")
    summary.csv, summary.md           final return mean +- std over seeds, the mean over each run's
                                      last tenth of env steps, env steps, wall-clock
    curves.png                        return vs env steps, mean +- std over seeds, a panel per env
                                      (and split), like the paper's Figures 5 and 6

The summary and the figure cover the runs asked for and every other finished run under ``--out``
(runs made by other commands into it: other seeds, envs or sittings); ``--summary-only`` makes
them without training anything. ``--also DIR[:ALGO,...]`` adds the finished runs of other folders
(of the named algorithms only, where named) to the summary and the figure, e.g. one algorithm's long
runs beside the baselines' shorter ones (Figure 6 from three folders)::

    python -m sb3_dream.experiments --envs MetaCook-v0 --eval-splits test train --summary-only \\
        --out results/cook_baselines --also results/cook_256_c001_lr1e5:dream results/cook_undo:rl2dqn

**Algorithms:** ``dream`` (:class:`~sb3_dream.DREAM`), ``dream_no_bottleneck``
(``DREAM(bottleneck=False)``, the paper's ablation), ``rl2dqn``
(:class:`~sb3_dream.rl2dqn.RL2DQN`, the paper's RL² baseline), ``import_dqn``
(:class:`~sb3_dream.IMPORT`) and ``varibad`` (:class:`~sb3_dream.VariBAD`), and ``e_rl2dqn``,
``e_import_dqn``, ``e_varibad``: the same with an instruction and rewards in the exploration
episode (the paper's dashed lines). ``--preset paper`` keeps every default (the paper's);
``--preset fast`` applies :data:`sb3_dream.presets.PRESETS` ``["fast"]`` to DREAM and the
matching schedule changes (``RL2DQN_PRESETS``, ``IMPORT_PRESETS``, ``VARIBAD_PRESETS``) to the
baselines; ``--preset laptop`` (DREAM only) adds the laptop preset's execution options.

**Envs** are registered IDs with optional constructor arguments after colons, e.g.
``MetaBus-v0:variant=map`` or ``MetaCook-v0:n_exec_episodes=2``. ``split`` there sets the
training split only; evaluation uses ``--eval-splits``.

Figure 5 (distracting bus and map) on a laptop-sized budget::

    python -m sb3_dream.experiments --envs MetaBus-v0 MetaBus-v0:variant=map \\
        --algos dream dream_no_bottleneck rl2dqn --seeds 0 1 2 --steps 200000 --preset fast \\
        --out results/figure5

matplotlib (a dev extra) is needed for the figure only; without it the figure is skipped.
"""

from __future__ import annotations

import argparse
import pathlib
from typing import Any, Dict, List, Optional, Sequence, Tuple

from dream_envs import all_splits
from sb3_dream.evaluation import BEST_TIES
from sb3_dream.experiments.algorithms import ALGORITHMS, override_fields, preset_names
from sb3_dream.experiments.backends import LocalPool
from sb3_dream.experiments.config import EnvSpec, RunConfig, parse_kwargs
from sb3_dream.experiments.lock import FolderLocked
from sb3_dream.experiments.report import (
    oracle_return,
    parse_folder_spec,
    plot_curves,
    report_folders,
    summarize,
    write_summary,
)
from sb3_dream.experiments.runner import check_eval_splits, check_presets, plan_runs, run_experiments


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_dream.experiments",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--algos", nargs="+", default=["dream"], help=f"any of {', '.join(ALGORITHMS)}")
    parser.add_argument("--envs", nargs="+", default=["MetaBus-v0"], help="env IDs, optionally ID:key=value...")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=100_000, help="env steps per run")
    parser.add_argument("--n-envs", type=int, default=1, help="vectorised envs per run")
    parser.add_argument("--preset", default="paper", choices=preset_names())
    parser.add_argument("--eval-freq", type=int, default=10_000, help="env steps between evaluations")
    parser.add_argument("--eval-trials", type=int, default=100, help="meta-test trials per evaluation")
    parser.add_argument(
        "--eval-exhaustive",
        action="store_true",
        help="evaluate on every (problem, instruction) pair of the split, weighted by its probability "
        "(the split's expected return; --eval-trials is then a minimum, in whole passes over the pairs)",
    )
    parser.add_argument(
        "--eval-splits",
        nargs="+",
        default=["test"],
        choices=all_splits(),
        help="test = held-out problems and instructions; MetaCook also has its parts test_problems, test_instructions",
    )
    for field in override_fields():
        algos = ", ".join(spec.name for spec in ALGORITHMS.values() if spec.overrides == field)
        parser.add_argument(
            _flag(field), nargs="*", default=[], metavar="KEY=VALUE", help=f"constructor overrides of {algos}"
        )
    parser.add_argument(
        "--backend",
        default="local",
        choices=("local", "ray"),
        help="where the runs execute: local = processes of this machine (--jobs); ray = Ray tasks on a "
        "cluster (--ray-address) or a local Ray",
    )
    parser.add_argument(
        "--jobs", type=int, default=None, help="parallel runs of the local backend (default: the machine's cores)"
    )
    parser.add_argument(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="--backend ray: the cluster's HOST:PORT (ray start --head prints it), ray://HOST:PORT or auto; "
        "default: a Ray started on this machine for the experiment",
    )
    parser.add_argument(
        "--cpus-per-run", type=float, default=None, help="--backend ray: CPUs each run reserves (default: --threads)"
    )
    parser.add_argument("--gpus-per-run", type=float, default=0, help="--backend ray: GPUs each run reserves")
    parser.add_argument(
        "--ray-files",
        default="shared",
        choices=("shared", "driver"),
        help="--backend ray: shared = the tasks write into --out, on a filesystem every node shares at the same "
        "path; driver = each task trains in a folder of its node and sends the run's files back to --out here",
    )
    parser.add_argument(
        "--max-retries",
        type=int,
        default=3,
        help="--backend ray: reruns of a run whose worker died (it goes on from its checkpoint with --checkpoint-freq)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--save-models", action="store_true", help="save each trained model next to its curve")
    parser.add_argument(
        "--checkpoint-freq",
        type=int,
        default=0,
        help="save model and replay buffers at least every N env steps (at evaluations) and resume from them; 0: off",
    )
    parser.add_argument(
        "--snapshot-freq",
        type=int,
        default=0,
        help="also save the model (no replay buffers) every N env steps under <env>/snapshots/; 0: off",
    )
    parser.add_argument(
        "--tensorboard",
        action="store_true",
        help="SB3's TensorBoard logs under <env>/tensorboard/ (tensorboard --logdir OUT): rollout/, train/, "
        "and each evaluated split (eval/: held out, eval_<split>/: the others); needs tensorboard installed",
    )
    parser.add_argument(
        "--select-on",
        default="",
        choices=("", *all_splits()),
        metavar="SPLIT",
        help="keep the model of the best evaluation on SPLIT (one of --eval-splits; train: an honest "
        "choice) under <env>/best/ and meta-test it on the held-out split at the end",
    )
    parser.add_argument(
        "--select-ties",
        default="last",
        choices=BEST_TIES,
        help="which of several evaluations at the same best return --select-on keeps (default last: on a "
        "saturated split, e.g. MetaCook's training split at the oracle, the first is an early model)",
    )
    parser.add_argument(
        "--init-from",
        default="",
        metavar="DIR",
        help="start each run from the same run's final checkpoint under DIR, with this command's overrides",
    )
    parser.add_argument("--out", default="results/experiments")
    parser.add_argument("--force", action="store_true", help="redo finished runs")
    parser.add_argument("--no-plot", action="store_true", help="skip the figure")
    parser.add_argument(
        "--summary-only",
        action="store_true",
        help="train nothing: summarize and plot the finished runs under --out (e.g. runs made by several "
        "commands into it)",
    )
    parser.add_argument(
        "--also",
        nargs="+",
        default=[],
        metavar="DIR[:ALGO,...]",
        help="the summary and the figure also cover the finished runs under DIR (only ALGO's, where named), "
        "e.g. long runs of one algorithm made into another folder; they are read, not written",
    )
    parser.add_argument("--no-oracle", action="store_true", help="skip the optimal scripted agent's return")
    return parser


def _check_tensorboard() -> None:
    """--tensorboard needs what SB3 logs with: say so before any run starts."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError as error:
        raise ValueError("--tensorboard needs tensorboard: pip install tensorboard") from error


def main(argv: Optional[Sequence[str]] = None) -> List[Dict[str, Any]]:
    """Run the experiment described by ``argv`` (see ``--help``); return the run records."""
    args = build_parser().parse_args(argv)
    try:
        config = RunConfig(
            steps=args.steps,
            n_envs=args.n_envs,
            preset=args.preset,
            eval_freq=args.eval_freq,
            eval_trials=args.eval_trials,
            eval_exhaustive=args.eval_exhaustive,
            eval_splits=tuple(dict.fromkeys(args.eval_splits)),
            threads=args.threads,
            device=args.device,
            save_models=args.save_models,
            checkpoint_freq=args.checkpoint_freq,
            snapshot_freq=args.snapshot_freq,
            tensorboard=args.tensorboard,
            select_on=args.select_on,
            select_ties=args.select_ties,
            init_from=args.init_from,
            **{
                field: tuple(sorted(parse_kwargs(getattr(args, field), _flag(field)).items()))
                for field in override_fields()
            },
        )
        runs = plan_runs(args.algos, [EnvSpec.parse(e) for e in args.envs], args.seeds)
        check_eval_splits(runs, config)
        check_presets(runs, config)
        if args.jobs is not None and args.jobs < 1:
            raise ValueError(f"jobs must be an integer >= 1, got {args.jobs}")
        if args.tensorboard and not args.summary_only:
            _check_tensorboard()
        backend = None if args.summary_only else _backend(args)
        also = [parse_folder_spec(spec) for spec in args.also]
    except ValueError as error:
        raise SystemExit(f"error: {error}")

    import dream_envs  # noqa: F401  (registers the env IDs in this process)

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        if backend is not None and args.backend == "ray" and args.ray_address is not None:
            backend.connect()  # a bad address stops here, before anything is locked or trained
        records = [] if args.summary_only else run_experiments(runs, config, out, force=args.force, backend=backend)
    except (FolderLocked, ConnectionError) as error:
        raise SystemExit(f"error: {error}")
    finally:
        if backend is not None and args.backend == "ray":
            backend.close()

    # The table and the figure cover every finished run under --out (and --also), not only this command's.
    try:
        folders = report_folders(runs, out, also)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"error: {error}")
    runs = list(folders)
    oracles: Dict[Tuple[str, str], float] = {}
    if not args.no_oracle:
        for env in dict.fromkeys(run.env for run in runs):
            for split in config.eval_splits:
                value = oracle_return(env, split, config.eval_trials, out, config.eval_exhaustive)
                if value is not None:
                    oracles[(env.tag, split)] = value
    table = write_summary(summarize(runs, config, out, oracles, folders=folders), out)
    print(f"\n{table}\nwrote {out / 'summary.csv'} and {out / 'summary.md'}")
    if not args.no_plot:
        try:
            print("wrote", plot_curves(runs, config, out, oracles, folders=folders))
        except ImportError:
            print("matplotlib is not installed: no figure (pip install matplotlib, or sb3-dream[dev])")
    failed = [r for r in records if r["status"] == "failed"]
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed")
    return records


def _backend(args: argparse.Namespace) -> Any:
    """The backend that ``args`` ask for (``--backend`` and its options)."""
    if args.backend == "local":
        ray_flags = [f for f, v in (("--ray-address", args.ray_address), ("--cpus-per-run", args.cpus_per_run)) if v]
        ray_flags += ["--gpus-per-run"] if args.gpus_per_run else []
        ray_flags += ["--ray-files"] if args.ray_files != "shared" else []
        if ray_flags:
            raise ValueError(f"{', '.join(ray_flags)} needs --backend ray")
        return LocalPool(args.jobs)
    if args.ray_files == "driver" and args.init_from:
        raise ValueError("--init-from reads the parent runs from a shared filesystem: use --ray-files shared")
    if args.jobs is not None:
        raise ValueError("--jobs is the local backend's; with --backend ray, --cpus-per-run and the cluster set it")
    from sb3_dream.experiments.ray_backend import RayBackend

    return RayBackend(
        address=args.ray_address,
        cpus_per_run=args.cpus_per_run if args.cpus_per_run is not None else args.threads,
        gpus_per_run=args.gpus_per_run,
        max_retries=args.max_retries,
        files=args.ray_files,
    )


def _flag(field: str) -> str:
    """The command-line flag of a RunConfig field: ``dream_kwargs`` -> ``--dream-kwargs``."""
    return "--" + field.replace("_", "-")
