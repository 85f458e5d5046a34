"""Training throughput of the authors' DREAM (github.com/ezliu/dream) on their bus ("city") grid.

Measures env steps per second of the authors' own training entry point (``main.py``: one
exploration episode then one execution episode per trial, both DQN agents learning), with the
paper's hyperparameters (``configs/default.json``), over ``--steps`` env steps after a
``--warmup``, so that docs can report it beside ``benchmarks/dream_speed.py`` measured in the
same sitting. Nothing is downloaded: ``--repo`` is a checkout (or ``git archive``) of ezliu/dream
that you supply; the script copies it to a temporary folder, applies the compatibility patches
listed below (checked: each must match, or the script stops naming the file), and runs
``main.main()`` in this process.

    python benchmarks/authors_speed.py --repo ~/src/dream --python ~/authors-venv/bin/python
    python benchmarks/authors_speed.py --repo ~/src/dream --steps 3000 --warmup 1000 [--environment map]

Ours, in the same sitting (its docs line: "paper hyperparameters: one exploration and one
execution update of batch 32 per 4 env steps, one torch thread"):

    python benchmarks/dream_speed.py --steps 3000 --n-envs 1 8

**What is timed.** The wall-clock from the start of the first trial that begins at or after
``--warmup`` env steps to the start of the first trial that begins at or after ``--warmup +
--steps``: everything the authors' training loop does in between (acting, env steps, both
agents' updates, the per-trial reward labelling, its tensorboard and text logging every 100
trials), except its periodic evaluation (every 2000 trials: 100 test trials and 10 rendered
train trials written as GIFs), whose time is measured and subtracted (``dream_speed.py`` does not
evaluate either). Both ends lie on trial boundaries, so every timed step has had its updates (the
exploration agent's updates run after its episode), and the timed count is within one trial (at
most 40 steps) of ``--steps``: the printed count is the one divided by the time.

**How steps are counted.** As the authors' loop counts them (``exploration_steps +
instruction_steps``): the lengths of the training episodes that ``main.run_episode`` returns,
read by wrapping ``main.run_episode`` from outside (the wrapper also raises to stop the run).
Updates are counted by wrapping ``dqn.RecurrentDQNPolicy.loss`` (one call per gradient update;
the exploration agent's is the one with a reward relabeler). Neither wrapper changes what runs.

**Install (Python 3.11, found to work beside torch 2.13.0; a separate venv):**

    python3 -m venv ~/authors-venv && . ~/authors-venv/bin/activate
    pip install torch==2.13.0            # the CPU build here; never an unpinned torch
    pip install gym==0.16.0 tensorboard tqdm Pillow

``gym==0.16.0`` is the authors' pin; it builds from its sdist on Python 3.11 and pulls
cloudpickle 1.2.2, pyglet 1.5.0, scipy and numpy (numpy 2.4.6 worked; gym 0.16's spaces are all
the city env uses). Tested with: numpy 2.4.6, scipy 1.17.1, tensorboard 2.21.0, tqdm 4.70.1,
Pillow 13.0.0. Not needed for the city env: gym-minigrid and gym-miniworld (only
``envs/miniworld``, imported for ``miniworld_sign`` only), GitPython (patch 2), torchvision,
scikit-learn, matplotlib. ``tensorboard`` is needed: ``utils.py`` imports
``torch.utils.tensorboard``.

**Patches (compatibility only; no algorithm, hyperparameter, network or update-ratio change):**

1. ``envs/city.py``, ``envs/grid.py``, ``embed.py``: ``np.int`` -> ``int``. NumPy 1.24 removed the
   alias; it was the builtin ``int`` itself, so the dtypes are unchanged (int64 here).
2. ``main.py``: drop ``import git`` and the ``git.Repo()`` lines that write the commit and the
   working-tree diff into ``metadata.txt``: the copy is no git repository (GitPython raises
   ``InvalidGitRepositoryError``). ``metadata.txt`` still gets its "Split:" line.

Left as they are: ``torch.set_default_tensor_type`` (deprecated in torch 2.x, still works; a
warning), the GPU branch in ``main.py`` (``--device cpu``, the default, hides CUDA through
``CUDA_VISIBLE_DEVICES`` so that both implementations are timed on the CPU; ``auto`` leaves the
authors' choice; the GPU path was not tried with torch 2.13), the tqdm bar (silenced with
``TQDM_DISABLE=1`` unless ``--progress``), and torch 2.13's warning that ``embed.py`` builds a
tensor from a list of numpy arrays (the authors' code, slow in torch 1.4 as well).

**Settings.** ``-c configs/default.json -b environment="distraction"`` is the paper's command for
the distracting bus (README "Distracting Bus"), the authors' counterpart of ``MetaBus-v0``'s
default variant ("distracting"); ``--environment map`` / ``vanilla`` give the map and plain
variants (``MetaBus-v0`` with ``variant="map"`` / ``"vanilla"``). ``configs/default.json`` holds the
paper's hyperparameters: batch 32 (episodes), ``update_freq`` 4, Adam 1e-4, target sync every
5000 of the agent's transitions, epsilon 1 -> 0.01 over 250K of the agent's actions, gradient
clipping at 10. (``main.py`` always loads ``configs/default.json`` first; ``-c`` merges on top.) The seed is passed as
``-s``. Torch threads: ``torch.set_num_threads(--threads)`` before ``main.main()`` (default 1, as
``dream_speed.py``).

**Where the authors' run differs from ours in what is timed:**

- Learning starts: the paper's ``min_buffer_size`` is 500 execution and 8000 exploration episodes
  (roughly 120K env steps, at the near-random start's episode lengths, before the exploration
  agent learns). As ``dream_speed.py`` (which sets
  ``exploration_learning_starts=execution_learning_starts=10`` trials), this script lowers both to
  ``--min-buffer-size`` (default 10 episodes, i.e. 10 trials) through the authors' own config
  bindings (``-b exploration_agent.min_buffer_size=10 -b instruction_agent.min_buffer_size=10``);
  ``--paper-starts`` keeps 500 / 8000 (then a ``--warmup`` under ~120K times only the execution
  agent learning).
- Update ratio: each agent's ``update_freq`` counts its own transitions, so the authors do one
  exploration update per 4 *exploration* steps and one execution update per 4 *execution* steps:
  about one update (of one agent or the other) per 4 env steps, where ours does one of each per 4
  env steps. The script prints the update counts it saw.
- Batches: the authors' execution update samples 32 whole execution episodes (up to 20
  transitions each, the horizon; ours by default 32 transitions, ``execution_sampling="episodes"``
  being the authors' way), and every execution update also runs the trajectory embedder (LSTM)
  on those 32 episodes' exploration trajectories, for the Q-network's and the target network's
  inputs and for its auxiliary loss; the exploration update relabels the rewards of its 32
  sampled trajectories with the same embedder.
- One env, stepped one trial at a time (the authors' loop has no vectorized envs): compare with
  ``dream_speed.py --n-envs 1``; its ``--n-envs 8`` has no authors' counterpart.
- Warmup: both start learning after 10 trials, but the authors' code also evaluates at trial 0
  (100 test trials, GIFs), which falls in the warmup and is not timed.
- Epsilon: both decay each policy's epsilon from 1 over 250K of its own steps, so a short run acts almost at random, and
  exploration episodes end early (the end-episode action is one of 9): the printed mean episode
  lengths show how long the timed trajectories were.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# (file, regular expression, replacement, expected number of matches, reason). Each must match
# exactly that many times, or the upstream code changed and the script stops.
PATCHES = [
    # 1. NumPy >= 1.24 removed np.int, an alias of the builtin int (same dtype, int64 here).
    ("envs/city.py", r"\bnp\.int\b", "int", 2, "np.int alias removed in NumPy 1.24"),
    ("envs/grid.py", r"\bnp\.int\b", "int", 3, "np.int alias removed in NumPy 1.24"),
    ("embed.py", r"\bnp\.int\b", "int", 1, "np.int alias removed in NumPy 1.24"),
    # 2. The copy is no git repository: skip GitPython's commit and diff in metadata.txt.
    ("main.py", r"(?m)^import git\n", "", 1, "GitPython needs a git repository"),
    (
        "main.py",
        re.escape(
            "    repo = git.Repo()\n"
            '    f.write("Commit: {}\\n\\n".format(repo.head.commit))\n'
            "    commit = repo.head.commit\n"
            "    diff = commit.diff(None, create_patch=True)\n"
            "    for patch in diff:\n"
            "      f.write(str(patch))\n"
            '      f.write("\\n\\n")\n'
        ),
        '    f.write("Commit: unknown (a patched copy, see sb3-dream benchmarks/authors_speed.py)\\n\\n")\n',
        1,
        "GitPython needs a git repository",
    ),
]

ENVIRONMENTS = ("distraction", "map", "vanilla")  # MetaBus-v0 variants distracting, map, vanilla


class _Stop(BaseException):
    """Raised from the run_episode wrapper once the timed steps are done (not an Exception, so
    that nothing in the authors' code can catch it)."""


def apply_patches(root: Path) -> None:
    for relative, pattern, replacement, expected, reason in PATCHES:
        path = root / relative
        if not path.is_file():
            raise SystemExit(f"patch ({reason}): {relative} not found in {root}: not a checkout of ezliu/dream?")
        text = path.read_text()
        found = len(re.findall(pattern, text))
        if found != expected:
            raise SystemExit(
                f"patch ({reason}) in {relative}: expected {expected} match(es) of {pattern!r}, found {found}; "
                "the upstream code changed, update PATCHES in benchmarks/authors_speed.py"
            )
        path.write_text(re.sub(pattern, lambda _: replacement, text))


def commit_of(repo: Path) -> str:
    try:
        out = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        return out.stdout.strip() if out.returncode == 0 else "unknown"
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"


def run(args: argparse.Namespace, work: Path) -> dict:
    """Runs the patched main.main() in this process; returns the timings of the window."""
    source = work / "dream"
    shutil.copytree(args.repo, source, ignore=shutil.ignore_patterns(".git", "experiments", "__pycache__"))
    apply_patches(source)
    config = source / args.config
    if not config.is_file():
        raise SystemExit(f"--config {args.config}: not found in {args.repo}")
    if args.device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # before torch loads: the authors' code takes a GPU if it sees one
    if not args.progress:
        os.environ["TQDM_DISABLE"] = "1"
    os.chdir(source)  # main.py reads configs/ and writes experiments/ relative to the working directory
    sys.path.insert(0, str(source))

    import torch

    torch.set_num_threads(args.threads)
    import dqn
    import main as authors_main

    stats = {"steps": 0, "trials": 0, "eval": 0.0, "exploration_updates": 0, "execution_updates": 0}
    window = {"start": None, "steps": 0, "trials": 0, "exp_steps": 0}
    state = {"eval_since": None, "exploration_len": 0, "execution_len": 0}
    target = args.warmup + args.steps
    run_episode = authors_main.run_episode

    def counted_run_episode(env, policy, experience_observers=None, test=False):
        now = time.perf_counter()
        if test:  # the periodic evaluation: from its first episode to the next training trial
            if state["eval_since"] is None:
                state["eval_since"] = now
            return run_episode(env, policy, experience_observers, test)
        if experience_observers is None:  # the exploration episode: a trial starts
            if state["eval_since"] is not None:
                if window["start"] is not None:
                    stats["eval"] += now - state["eval_since"]
                state["eval_since"] = None
            if window["start"] is None and stats["steps"] >= args.warmup:
                window.update(start=now, steps=stats["steps"], trials=stats["trials"])
                stats.update(eval=0.0, exploration_updates=0, execution_updates=0)
                state.update(exploration_len=0, execution_len=0)
            if stats["steps"] >= target:
                stats["end"] = now
                raise _Stop
            stats["trials"] += 1
        episode, renders = run_episode(env, policy, experience_observers, test)
        stats["steps"] += len(episode)  # as the authors' exploration_steps + instruction_steps
        state["execution_len" if experience_observers else "exploration_len"] += len(episode)
        return episode, renders

    authors_main.run_episode = counted_run_episode
    loss = dqn.RecurrentDQNPolicy.loss

    def counted_loss(self, experiences, weights):
        key = "exploration_updates" if self._reward_relabeler is not None else "execution_updates"
        stats[key] += 1
        return loss(self, experiences, weights)

    dqn.RecurrentDQNPolicy.loss = counted_loss

    bindings = [f'environment="{args.environment}"']
    if not args.paper_starts:
        for agent in ("exploration_agent", "instruction_agent"):  # the authors' own config bindings
            bindings.append(f"{agent}.min_buffer_size={args.min_buffer_size}")
    sys.argv = ["main.py", "benchmark", "-c", args.config, "-x", str(work / "experiments"), "-s", str(args.seed), "-f"]
    for binding in bindings:
        sys.argv += ["-b", binding]
    print("authors' command:", " ".join(sys.argv), flush=True)
    try:
        authors_main.main()
    except _Stop:
        pass
    else:
        raise SystemExit("the authors' main() returned before the timed steps were done")
    trials = stats["trials"] - window["trials"]
    return {
        "wall": stats["end"] - window["start"] - stats["eval"],
        "eval": stats["eval"],
        "steps": stats["steps"] - window["steps"],
        "trials": trials,
        "exploration_len": state["exploration_len"] / trials,
        "execution_len": state["execution_len"] / trials,
        "exploration_updates": stats["exploration_updates"],
        "execution_updates": stats["execution_updates"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", required=True, type=Path, help="a checkout or git archive of ezliu/dream")
    parser.add_argument("--steps", type=int, default=3000, help="timed env steps (after the warmup)")
    parser.add_argument("--warmup", type=int, default=1000, help="env steps before the timing starts")
    parser.add_argument(
        "--config", default="configs/default.json", help="authors' config (relative to --repo), merged on default.json"
    )
    parser.add_argument(
        "--environment", default="distraction", choices=ENVIRONMENTS, help="authors' bus env (MetaBus-v0 variant)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--min-buffer-size", type=int, default=10, help="both agents' learning start, in episodes (ours: 10 trials)"
    )
    parser.add_argument("--paper-starts", action="store_true", help="keep the paper's 500 / 8000 episodes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", choices=["cpu", "auto"], help="cpu hides CUDA from torch")
    parser.add_argument("--progress", action="store_true", help="show the authors' tqdm bar")
    parser.add_argument("--keep", type=Path, help="work in this new folder and keep it (patched copy, logs)")
    parser.add_argument("--python", help="run under this interpreter (the venv with the authors' dependencies)")
    args = parser.parse_args()
    if args.python and not os.environ.get("AUTHORS_SPEED_CHILD"):
        env = {**os.environ, "AUTHORS_SPEED_CHILD": "1"}
        sys.exit(subprocess.run([args.python, os.path.abspath(__file__), *sys.argv[1:]], env=env).returncode)
    args.repo = args.repo.expanduser().resolve()
    if not (args.repo / "main.py").is_file() or not (args.repo / "envs" / "city.py").is_file():
        parser.error(f"--repo {args.repo}: no main.py and envs/city.py: not a checkout of ezliu/dream")
    if args.steps <= 0 or args.warmup < 0:
        parser.error("--steps must be positive and --warmup not negative")
    if args.keep:
        args.keep = args.keep.expanduser().resolve()
        if args.keep.exists() and any(args.keep.iterdir()):
            parser.error(f"--keep {args.keep}: not empty")
        args.keep.mkdir(parents=True, exist_ok=True)
        work, cleanup = args.keep, None
    else:
        cleanup = tempfile.TemporaryDirectory(prefix="authors_speed_")
        work = Path(cleanup.name)
    commit = commit_of(args.repo)
    try:
        result = run(args, work)
    finally:
        os.chdir("/")
        if cleanup is not None:
            cleanup.cleanup()
    starts = "500 / 8000 (paper)" if args.paper_starts else f"{args.min_buffer_size} / {args.min_buffer_size}"
    print(
        f"\nauthors' DREAM (ezliu/dream {commit[:12]}), environment={args.environment}, {args.config}, "
        f"min_buffer_size execution / exploration {starts}, {args.threads} torch thread(s), seed {args.seed}"
    )
    print(
        f"{result['steps'] / result['wall']:.1f} env steps/s: {result['steps']} env steps ({result['trials']} trials)"
        f" in {result['wall']:.1f} s after {args.warmup} warmup steps"
        + (f" (evaluation, {result['eval']:.1f} s, not counted)" if result["eval"] else "")
    )
    exploration, execution = result["exploration_updates"], result["execution_updates"]
    print(
        f"updates: {exploration} exploration + {execution} execution, batch 32"
        f" ({4 * exploration / result['steps']:.2f} + {4 * execution / result['steps']:.2f} per 4 env steps;"
        f" ours: 1 + 1); mean episode length: exploration {result['exploration_len']:.1f},"
        f" execution {result['execution_len']:.1f}"
    )
    if args.keep:
        print(f"kept: {args.keep}")


if __name__ == "__main__":
    main()
