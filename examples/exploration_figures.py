"""What saved models explore, drawn on the grid (the paper's Figures 7, 8), and DREAM's codes (Figure 9).

    python examples/exploration_figures.py --env-kwargs variant=map --trials 5 \\
        --model DREAM=models/dream_metabus_map.zip --model RL2DQN=models/rl2dqn_metabus_map.zip \\
        --out results/exploration_figures/metabus_map
    python examples/exploration_figures.py --model dream_bus.zip --model "no bottleneck=dream_nb.zip" \\
        --trials 3 --out bus                                   # the distracting bus (Figure 7a, b)
    python examples/exploration_figures.py --env MetaCook-v0 --model dream_cook.zip --out cook   # Figure 8
    python examples/exploration_figures.py --env-kwargs variant=map --codes --trials 96 \\
        --model DREAM=models/dream_metabus_map.zip --out results/exploration_figures/metabus_map
    python examples/exploration_figures.py --oracle --env-kwargs variant=map --out oracle_map

**Explorations** (``<out>_explorations.png`` and ``.csv``): each ``--model`` (``LABEL=PATH``, or a
bare path labelled by its file name; DREAM, RL2DQN, or any saved model whose class offers
``as_trial_agent``) plays ``--trials`` greedy trials on the same held-out problems (``--split``, an
order drawn with ``--seed``), and each model's exploration episodes are drawn in one panel, side by
side: the grid once, each trial's path in its own colour and shifted by a small offset, a dashed
arc per bus ride, a star where a bus was ridden or a fridge opened, a ring where the map was read.
The legend names each trial's problem and what its exploration found; the panel's title sums it up.
``--oracle`` adds the env's scripted optimal explorer as a panel. A model trained with an
instruction and rewards in its exploration episodes (the runner's ``e_rl2dqn``, ``e_import_dqn``,
``e_varibad``: the paper's dashed lines) plays in the env with ``reward_free_exploration=False``,
as it was trained, on the same problems as the other panels. The CSV holds every plotted point
(panel, trial, problem, step, cell, drawn position, action, what the step found).

**Codes** (``--codes``, ``<out>_codes.png`` and ``.csv``; the first DREAM ``--model``): f(T) of every
problem and g(tau^exp) of ``--trials`` held-out explorations in 2-D, with t-SNE where scikit-learn is
installed and PCA otherwise (``--embedding``), coloured by ``--color-by`` (a problem feature index,
default 0: MetaBus's colored permutation, the part of the problem that matters; or ``problem``), and
the decoder's reading step by step (g(tau_:t)) of the first ``--prefix-paths`` trials. Reads each
trial's problem: a diagnostic (see ``sb3_dream.code_figures``).
"""

from __future__ import annotations

import argparse
import csv
import pathlib
from typing import Any, Dict, List, Optional, Sequence, Tuple

import gymnasium as gym

import dream_envs
from dream_envs import make_oracle
from dream_envs.figures import (
    FAMILIES,
    PATH_COLUMNS,
    exploration_figure,
    exploration_paths,
    held_out_problems,
    path_rows,
)
from sb3_dream.code_figures import CODE_COLUMNS, EMBEDDINGS, code_distances, code_figure, dream_codes
from sb3_dream.common.files import atomic_target
from sb3_dream.evaluation import as_trial_agent
from sb3_dream.experiments import parse_kwargs
from sb3_dream.loading import load_model


def parse_model_args(values: Sequence[str]) -> List[Tuple[str, str]]:
    """``LABEL=PATH`` or ``PATH`` (labelled by its file name) -> (label, path), checking that each file
    exists and that labels differ; a ``ValueError`` naming ``--model`` otherwise."""
    models: List[Tuple[str, str]] = []
    for value in values:
        label, sep, path = value.partition("=")
        if not sep or not label or not path.strip() or label.endswith(".zip"):
            label, path = pathlib.Path(value).stem, value
        if not pathlib.Path(path).is_file():
            raise ValueError(f"--model: no such file: {path}")
        if label in dict(models):
            raise ValueError(f"--model: the label {label!r} is given twice; label each model (LABEL=PATH)")
        models.append((label, path))
    return models


def write_csv(path: pathlib.Path, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """``rows`` under a header of ``columns``, written whole or not at all."""
    with atomic_target(path, "csv") as tmp, open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows(rows)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", action="append", default=[], metavar="[LABEL=]PATH",
                        help="a saved model (repeatable; one panel each, in the order given)")  # fmt: skip
    parser.add_argument("--env", default="MetaBus-v0", help=f"one of {', '.join(FAMILIES)}")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="as in training, e.g. variant=map"
    )
    parser.add_argument("--split", default="test", choices=dream_envs.all_splits(), help="test = held-out problems")
    parser.add_argument(
        "--trials", type=int, default=4, help="trials (problems) drawn per panel; with --codes, g's trials"
    )
    parser.add_argument("--seed", type=int, default=0, help="draws the problems; trial k is seeded SEED + k")
    parser.add_argument("--oracle", action="store_true", help="add the env's scripted optimal explorer as a panel")
    parser.add_argument("--codes", action="store_true", help="draw the first DREAM model's codes (Figure 9) instead")
    parser.add_argument(
        "--embedding", default="auto", choices=EMBEDDINGS, help="auto: t-SNE with scikit-learn, else PCA"
    )
    parser.add_argument("--color-by", default="0", metavar="FEATURE|problem",
                        help="--codes: colour by this problem feature (index) or by the problem ID")  # fmt: skip
    parser.add_argument(
        "--prefix-paths", type=int, default=3, help="--codes: trials whose g(tau_:t) is drawn step by step"
    )
    parser.add_argument(
        "--out", required=True, help="path prefix: writes <out>_explorations.png/.csv or <out>_codes.png/.csv"
    )
    return parser


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse bad arguments with a message naming the argument (argparse's exit status 2)."""
    if args.env.split(":")[-1] not in FAMILIES:
        parser.error(f"--env must be one of {', '.join(FAMILIES)} (grid worlds drawn from above), got {args.env!r}")
    if args.trials < 1:
        parser.error(f"--trials must be a number of trials >= 1, got {args.trials}")
    if args.prefix_paths < 0:
        parser.error(f"--prefix-paths must be a number of trials >= 0, got {args.prefix_paths}")
    if args.color_by != "problem" and not args.color_by.isdigit():
        parser.error(f"--color-by must be a problem feature index (0, 1, ...) or 'problem', got {args.color_by!r}")
    if not args.model and not (args.oracle and not args.codes):
        parser.error("--model is required (with --codes, a DREAM model; without, --oracle alone also draws)")
    out = pathlib.Path(args.out)
    if out.name in ("", ".", "..") or out.is_dir():
        parser.error(
            f"--out must be a path prefix such as figures/map (files <out>_explorations.png ...), got {args.out!r}"
        )


def make_env(parser: argparse.ArgumentParser, args: argparse.Namespace, kwargs: Dict[str, Any]) -> gym.Env:
    try:
        return gym.make(args.env, split=args.split, **kwargs)
    except (TypeError, ValueError) as error:
        parser.error(f"--env-kwargs {' '.join(args.env_kwargs)} for {args.env}: {error}")
        raise  # unreachable: parser.error exits


def check_model_env(parser: argparse.ArgumentParser, path: str, model: Any, env: gym.Env) -> None:
    """Refuse a model trained in another trial shape (it would act on garbage, or fail deep inside):
    its trial spec where it kept one, its observation space always (a slimmed model keeps no spec)."""
    what = "the env (--env, --env-kwargs)"
    try:
        if hasattr(model, "check_trial_env"):
            model.check_trial_env(env, what, ignore=("n_exec_episodes",))
    except ValueError as error:
        parser.error(f"--model {path}: {error}")
    space = getattr(model, "observation_space", None)
    if space is not None and space != env.observation_space:
        parser.error(
            f"--model {path}: {what} does not match the model: the model observes {space}, "
            f"the env {env.observation_space}"
        )


def model_env(
    parser: argparse.ArgumentParser, args: argparse.Namespace, kwargs: Dict[str, Any], model: Any, env: gym.Env
) -> gym.Env:
    """``env``, or where ``model`` was trained with rewards in the exploration episode (the paper's
    dashed lines: E-RL2 and the like; its saved trial spec says so) and ``--env-kwargs`` leave that
    setting to the default, the same env with ``reward_free_exploration=False``: the model reads
    the exploration episode's instruction and rewards, and its panel shows what it explores there."""
    spec = getattr(model, "trial_spec", None) or {}
    wanted = spec.get("reward_free_exploration")
    if wanted is None or wanted == env.unwrapped.reward_free_exploration or "reward_free_exploration" in kwargs:
        return env
    return make_env(parser, args, {**kwargs, "reward_free_exploration": wanted})


def draw_explorations(
    args: argparse.Namespace, envs: Dict[str, gym.Env], models: Dict[str, Any], out: pathlib.Path
) -> Dict[str, Any]:
    """Play each model's trials (in its env of ``envs``) on the same problems, draw the panels
    and write the PNG and CSV."""
    env = next(iter(envs.values()))
    problem_ids = held_out_problems(env, args.trials, args.seed)
    panels = {}
    for label, model in models.items():
        agent = make_oracle(envs[label]) if model is None else as_trial_agent(model)
        panels[label] = exploration_paths(envs[label], agent, args.trials, args.seed, problem_ids)
    variant = getattr(env.unwrapped, "variant", None)
    title = f"{args.env}{f' ({variant})' if variant else ''}: exploration episodes, {args.split} split"
    png, table = out.with_name(out.name + "_explorations.png"), out.with_name(out.name + "_explorations.csv")
    with atomic_target(png, "png") as tmp:
        exploration_figure(env, panels, tmp, title=title)
    write_csv(table, PATH_COLUMNS, path_rows(env, panels))
    print(f"wrote {png} and {table}")
    return panels


def draw_codes(args: argparse.Namespace, kwargs: Dict[str, Any], models: Dict[str, Any], out: pathlib.Path) -> str:
    """The first DREAM model's codes in 2-D: write the PNG and CSV, return the embedding used."""
    from sb3_dream import DREAM

    dreams = [(label, m) for label, m in models.items() if isinstance(m, DREAM)]
    if not dreams:
        raise ValueError("--codes needs a DREAM --model (the codes are its encoder's and decoder's)")
    label, model = dreams[0]
    color_by = "problem" if args.color_by == "problem" else int(args.color_by)
    codes = dream_codes(model, args.env, args.trials, args.split, args.seed, kwargs)
    png, table = out.with_name(out.name + "_codes.png"), out.with_name(out.name + "_codes.csv")
    with atomic_target(png, "png") as tmp:
        try:
            _, rows, used = code_figure(codes, tmp, color_by, args.embedding, args.prefix_paths, args.seed,
                                        title=None)  # fmt: skip
        except ValueError as error:
            raise ValueError(f"--color-by: {error}") if "color_by" in str(error) else error
    write_csv(table, CODE_COLUMNS, rows)
    print(f"wrote {png} and {table} ({label}, {used})")
    distances = code_distances(codes)
    print(
        f"||g(tau^exp) - f(T)||^2 {distances['decoder_error']:.3f}, ||g(empty) - mean f||^2 "
        f"{distances['empty_to_mean_f']:.3f}, against ||f(T) - mean f||^2 {distances['f_spread']:.3f}"
    )
    return used


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(parser, args)
    try:
        kwargs = parse_kwargs(args.env_kwargs, "--env-kwargs")
        model_paths = parse_model_args(args.model)
    except ValueError as error:
        parser.error(str(error))
    env = make_env(parser, args, kwargs)
    models: Dict[str, Any] = {}
    envs: Dict[str, gym.Env] = {}
    if args.oracle and not args.codes:
        models["optimal (scripted)"], envs["optimal (scripted)"] = None, env
    for label, path in model_paths:
        try:
            model = load_model(path)
        except ValueError as error:
            parser.error(f"--model {path}: {error}")
        envs[label] = model_env(parser, args, kwargs, model, env)
        check_model_env(parser, path, model, envs[label])
        models[label] = model
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        if args.codes:
            draw_codes(args, kwargs, models, out)
        else:
            draw_explorations(args, envs, models, out)
    except (ValueError, ImportError) as error:
        parser.error(str(error))
    finally:
        for each in {id(e): e for e in [env, *envs.values()]}.values():
            each.close()


if __name__ == "__main__":
    main()
