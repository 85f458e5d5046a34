"""One run: train an algorithm on an env with a seed, evaluate it along the way, record it."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import time
from typing import Any, Dict

from sb3_dream.common.files import atomic_target
from sb3_dream.evaluation import format_mean_ci
from sb3_dream.experiments.algorithms import (
    algorithm_class,
    algorithm_env_kwargs,
    algorithm_spec,
    load_with_overrides,
    make_model,
)
from sb3_dream.experiments.checkpoints import (
    Checkpointer,
    init_checkpoint,
    make_checkpoint_callback,
    resume_best,
)
from sb3_dream.experiments.config import Run, RunConfig, split_suffix


def run_one(run: Run, config: RunConfig, out: pathlib.Path, concurrent_runs: int = 1) -> Dict[str, Any]:
    """Train and evaluate one run; its files appear under their final names only once complete.

    With ``config.checkpoint_freq`` it goes on from the run's last checkpoint, if there is one.
    ``concurrent_runs``: how many runs share the machine's cores with this one.
    """
    import torch as th
    from stable_baselines3.common.callbacks import CallbackList
    from stable_baselines3.common.env_util import make_vec_env

    th.set_num_threads(config.threads)
    folder = run.folder(out)
    folder.mkdir(parents=True, exist_ok=True)
    partial = {split: _partial(run.curve_path(out, split)) for split in config.eval_splits}
    checkpointer = Checkpointer(run, config, out)
    resume = checkpointer.load() if config.checkpoint_freq else None
    if resume is None:
        for path in partial.values():
            path.unlink(missing_ok=True)  # an interrupted run starts over
        for log in run.tensorboard_folder(out).glob(f"{run.name}_*"):
            shutil.rmtree(log, ignore_errors=True)  # and so does its TensorBoard log

    tag = f"{run.algo} {run.env.label} seed {run.seed}"
    init_from, resume_folder = None, checkpointer.folder  # init_from: starting from the parent now
    if resume is None and config.init_from:
        resume_folder, resume = init_checkpoint(run, config)
        init_from = {"out": config.init_from, "env_steps": int(resume["env_steps"])}
    checkpointer.init_from = init_from if init_from is not None else (resume or {}).get("init_from")
    env = make_vec_env(run.env.env_id, n_envs=config.n_envs, seed=run.seed, env_kwargs=run.env_kwargs)
    if resume is None:
        model, seconds_before = make_model(run.algo, env, config, run.seed), 0.0
    else:
        if init_from is None:
            model = algorithm_class(run.algo).load(resume_folder / resume["model"], env=env, device=config.device)
        else:
            model = load_with_overrides(run.algo, resume_folder / resume["model"], env, config)
        model.load_replay_buffer(resume_folder / resume["replay_buffer"])
        # make_vec_env seeded the envs as at step 0: without a seed of its own, the resumed run
        # would draw the same problems and instructions again, in the same order.
        model.env.seed(run.seed + model.num_timesteps)
        seconds_before = float(resume["train_seconds"])
        what = "its checkpoint" if init_from is None else f"the checkpoint under {config.init_from}"
        print(f"[{tag}] going on from {what} at {model.num_timesteps} env steps", flush=True)
    # set on every start, so a resumed run logs where this command says (a saved model keeps its own)
    model.tensorboard_log = str(run.tensorboard_folder(out)) if config.tensorboard else None
    if config.tensorboard and resume is not None:
        # SB3 goes on in the highest <name>_N it finds (or makes _0): make it _1 wherever the run goes on
        (run.tensorboard_folder(out) / f"{run.name}_1").mkdir(parents=True, exist_ok=True)
    spec = algorithm_spec(run.algo)
    if spec.prepare is not None:
        spec.prepare(model, config.overrides(run.algo), concurrent_runs)
    callbacks = [
        _make_progress_callback(
            tag if len(config.eval_splits) == 1 else f"{tag} {split}",
            eval_env=run.env.env_id,
            eval_freq=config.eval_freq,
            split=split,
            csv_path=str(partial[split]),
            best_model_save_path=str(run.best_folder(out)) if split == config.select_on else None,
            best_ties=config.select_ties,
            log_prefix=f"eval{split_suffix(split)}/",
            **_meta_test_kwargs(run, config),
        )
        for split in config.eval_splits
    ]
    best = next((cb for cb in callbacks if cb.best_model_save_path is not None), None)
    if best is not None and resume is None:
        shutil.rmtree(run.best_folder(out), ignore_errors=True)  # a fresh run selects afresh
    if resume is not None:
        for callback in callbacks:
            callback.resume(resume["curves"][callback.split])
        if best is not None:
            resume_best(best, resume, resume_folder, tag)
    callback_list = list(callbacks)
    if config.checkpoint_freq:
        callback_list.append(make_checkpoint_callback(checkpointer, callbacks, seconds_before, best))
    if config.snapshot_freq:
        from stable_baselines3.common.callbacks import CheckpointCallback

        # save_freq counts calls, one per vec-env step of n_envs env steps
        callback_list.append(
            CheckpointCallback(max(config.snapshot_freq // config.n_envs, 1), str(folder / "snapshots"), run.name)
        )
    start = time.perf_counter()
    model.learn(
        max(config.steps - model.num_timesteps, 0) if resume else config.steps,
        callback=CallbackList(callback_list),
        tb_log_name=run.name,  # SB3 adds _1, and a resumed run (reset_num_timesteps=False) goes on in it
        reset_num_timesteps=resume is None,
    )
    seconds = seconds_before + time.perf_counter() - start
    env.close()

    if config.checkpoint_freq and checkpointer.saved_steps() != model.num_timesteps:
        # Kept once the run is complete, so that a larger budget later extends it.
        checkpointer.save(model, {cb.split: cb.results for cb in callbacks}, seconds, best)
    if config.save_models:
        with atomic_target(run.model_path(out), "zip") as tmp:
            model.save(tmp)
    finals = {split: cb.results[-1] for split, cb in zip(config.eval_splits, callbacks)}
    info = {
        "algo": run.algo,
        "env": run.env.env_id,
        "env_kwargs": run.env.env_kwargs,
        "seed": run.seed,
        "settings": config.settings(run.algo),
        "train_seconds": seconds,
        "resumed_from": None if resume is None or init_from is not None else resume["env_steps"],
        "init_from": checkpointer.init_from,
        "final": finals,
    }
    fixed = algorithm_env_kwargs(run.algo)
    if fixed:
        info["algo_env_kwargs"] = fixed  # the env arguments the algorithm's name set (E-RL²'s)
    if best is not None and best.best_env_steps is not None:
        info["best"] = _meta_test_best(run, config, best, tag)
    if spec.report is not None:
        info.update(spec.report(model, run, config, tag))
    with atomic_target(run.info_path(out), "json") as tmp:
        tmp.write_text(json.dumps(info, indent=2, default=str))
    # The held-out curve (the completion mark) is renamed last.
    for split in sorted(config.eval_splits, key=lambda s: s == "test"):
        os.replace(partial[split], run.curve_path(out, split))
    return {"run": run, "status": "done", "seconds": seconds, "final": finals}


def _meta_test_best(run: Run, config: RunConfig, best: Any, tag: str) -> Dict[str, Any]:
    """The ``--select-on`` best model's return on the held-out split (the same trials as the curve)."""
    from sb3_dream.evaluation import evaluate_meta

    model = algorithm_class(run.algo).load(pathlib.Path(best.best_model_save_path) / "best_model.zip")
    result = evaluate_meta(model, run.env.env_id, split="test", **_meta_test_kwargs(run, config))
    print(
        f"[{tag}] best on {best.split}: {best.best_mean_reward:.3f} at {best.best_env_steps} env steps; "
        f"held-out return {format_mean_ci(result.mean, result.ci)}",
        flush=True,
    )
    return {
        "selected_on": best.split,
        "ties": best.best_ties,
        "env_steps": best.best_env_steps,
        "mean_on_selection_split": best.best_mean_reward,
        "test": {"mean": result.mean, "ci": result.ci, "exploration_length": result.mean_exploration_length},
    }


def _meta_test_kwargs(run: Run, config: RunConfig) -> Dict[str, Any]:
    """The trials of every meta-test of a run (curves, best model): seed 0, so that every run and
    evaluation meets the same problems, a paired comparison."""
    return {
        "n_trials": config.eval_trials,
        "exhaustive": config.eval_exhaustive,
        "n_exec_episodes": run.env.n_exec_episodes,
        "seed": 0,
        "env_kwargs": run.eval_kwargs,
    }


def _make_progress_callback(tag: str, **kwargs: Any) -> Any:
    """A :class:`MetaEvalCallback` that prints one tagged line per evaluation (runs share a terminal)."""
    from sb3_dream.evaluation import MetaEvalCallback

    class TaggedMetaEvalCallback(MetaEvalCallback):
        def _evaluate(self) -> None:
            super()._evaluate()
            row = self.results[-1]
            print(
                f"[{tag}] {row['env_steps']:>8} steps {row['wall_clock_s']:7.0f}s  {self.split} return "
                f"{format_mean_ci(row['mean'], row['ci'])}  exploration length {row['exploration_length']:.1f}",
                flush=True,
            )

    return TaggedMetaEvalCallback(**kwargs)


def _partial(path: pathlib.Path) -> pathlib.Path:
    return path.with_name(path.name + ".partial")
