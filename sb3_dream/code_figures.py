"""DREAM's codes in two dimensions (the paper's Figure 9): the encoder's f(T) and the decoder's g(tau^exp).

:func:`dream_codes` reads a trained DREAM model's codes: f(T) of every problem of the env (the
encoder's mean, no noise) and, over greedy meta-test trials, g(tau^exp) of each exploration and
g(tau_:t) of each of its prefixes (what the decoder makes of the trajectory so far,
:meth:`sb3_dream.DREAM.decode_prefixes`). It reads each trial's problem, so it is a diagnostic,
like :func:`sb3_dream.dream.diagnose`.

:func:`embed_2d` maps the codes to the plane, all of them together: with t-SNE where scikit-learn is
installed (the paper's choice), else with PCA (numpy). :func:`code_figure` draws them, coloured by
one part of the problem (e.g. MetaBus's colored permutation: the part that matters for execution):
f(T) as dots, g(tau^exp) as crosses in its problem's colour, and the prefixes of a few trials as a
line from g of the empty trajectory to g(tau^exp). A decoder that reads the exploration puts each
cross on its problem's dots; the prefix line shows when the exploration found what it needed.
:func:`code_rows` gives the plotted points as table rows.

matplotlib is imported only by :func:`code_figure` (an optional dependency of the package).
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple, Union

import gymnasium as gym
import numpy as np

from dream_envs.checks import check_positive_int
from dream_envs.figures import held_out_problems
from dream_envs.play import play_trials_batched

EMBEDDINGS = ("auto", "tsne", "pca")
CODE_COLUMNS = ("kind", "trial", "problem_id", "step", "color_value", "x", "y")
# What each problem feature is, per family (dream_envs' problem_features), for the colour bar.
FEATURE_NAMES: Dict[str, Tuple[str, ...]] = {
    "MetaBusEnv": ("colored permutation (where buses A-D lead)",)
    + tuple(f"gray bus g{k} destination" for k in range(1, 5)),
    "MetaCookEnv": tuple(f"fridge F{k} ingredient - 1" for k in range(3)),
}


@dataclass
class DreamCodes:
    """A DREAM model's codes: f over problems, g over meta-test trials (see :func:`dream_codes`)."""

    problem_ids: np.ndarray  # [n_problems] every problem of the env
    f: np.ndarray  # [n_problems, z] f(T), the encoder's mean
    features: np.ndarray  # [n_problems, d] each problem's features (problem_features)
    trial_problem_ids: np.ndarray  # [n_trials] trial k's problem
    g: np.ndarray  # [n_trials, z] g(tau^exp) of trial k's exploration
    prefixes: List[np.ndarray]  # trial k's g(tau_:t) for t = 0..T [T + 1, z]; the last is g[k]
    family: str = ""  # the env's class name


def dream_codes(
    model: Any,
    env: Union[str, gym.Env],
    n_trials: int = 96,
    split: str = "test",
    seed: int = 0,
    env_kwargs: Optional[Dict[str, Any]] = None,
    n_envs: int = 8,
) -> DreamCodes:
    """Play ``n_trials`` greedy meta-test trials of the DREAM ``model`` on ``split`` (its problems in an
    order drawn with ``seed``, each once before any repeats: :func:`dream_envs.figures.held_out_problems`)
    and read its codes: f(T) of every problem of the env, and g of each exploration and of its prefixes."""
    from sb3_dream.dream import DREAM, PrivilegedBatchAgent
    from sb3_dream.evaluation import make_envs

    if not isinstance(model, DREAM):
        raise TypeError(
            f"model must be a DREAM model (the codes are its encoder's and decoder's), got {type(model).__name__}"
        )
    n_trials = check_positive_int("n_trials", n_trials)
    envs, made = make_envs(env, split, 1, env_kwargs, min(check_positive_int("n_envs", n_envs), n_trials))
    try:
        for e in envs:
            model.check_trial_env(e, "the env", ignore=("n_exec_episodes",))
        trial_env = envs[0].unwrapped
        ids = held_out_problems(envs[0], n_trials, seed, split)
        agent = PrivilegedBatchAgent(model, ids, "g", seed)
        play_trials_batched(envs, agent, n_trials, seed, ids)
        all_ids = np.arange(trial_env.n_problems)
        features = trial_env.problem_feature_table()
    finally:
        for e in made:
            e.close()
    trajectories = [agent.trajectories[k] for k in range(n_trials)]
    return DreamCodes(
        problem_ids=all_ids,
        f=model.encode(all_ids, noisy=False),
        features=features,
        trial_problem_ids=np.asarray(ids, dtype=np.int64),
        g=agent.codes(),
        prefixes=model.decode_prefixes(trajectories),
        family=type(trial_env).__name__,
    )


def code_distances(codes: DreamCodes) -> Dict[str, float]:
    """Where the decoder's codes sit, in the codes' own space (no embedding): the mean squared
    distance of g(tau^exp) from its problem's f(T) (``decoder_error``), of g of the empty trajectory
    from the mean of f over the problems (``empty_to_mean_f``: the decoder's guess before it has seen
    anything, best at that mean when the problems are equally likely), and of f(T) from that mean
    (``f_spread``, the scale to read both against)."""
    mean_f = codes.f.mean(axis=0)
    empty = np.stack([prefix[0] for prefix in codes.prefixes])
    return {
        "decoder_error": float(((codes.g - codes.f[codes.trial_problem_ids]) ** 2).sum(axis=1).mean()),
        "empty_to_mean_f": float(((empty - mean_f) ** 2).sum(axis=1).mean()),
        "f_spread": float(((codes.f - mean_f) ** 2).sum(axis=1).mean()),
    }


def pca_2d(points: np.ndarray) -> np.ndarray:
    """``points`` [n, z] projected on their two principal axes (numpy; zeros where z < 2)."""
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    out = np.zeros((len(points), 2))
    k = min(2, vt.shape[0])
    out[:, :k] = centred @ vt[:k].T
    return out


def embed_2d(points: np.ndarray, method: str = "auto", seed: int = 0) -> Tuple[np.ndarray, str]:
    """``points`` [n, z] in the plane, and the method used: "tsne" (scikit-learn's t-SNE, the paper's
    choice), "pca" (numpy), or "auto": t-SNE where scikit-learn can be imported, else PCA."""
    if method not in EMBEDDINGS:
        raise ValueError(f"embedding={method!r} is not valid; accepted values: {', '.join(EMBEDDINGS)}")
    points = np.asarray(points, dtype=np.float64)
    if method == "pca":
        return pca_2d(points), "pca"
    try:
        from sklearn.manifold import TSNE
    except ImportError:
        if method == "tsne":
            raise ImportError("embedding='tsne' needs scikit-learn (pip install scikit-learn); use 'pca' or 'auto'")
        return pca_2d(points), "pca"
    # t-SNE needs perplexity < n; the default 30 for any but tiny sets
    perplexity = float(min(30.0, max(1.0, (len(points) - 1) / 3)))
    tsne = TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed)
    return tsne.fit_transform(points), "tsne"


def color_values(codes: DreamCodes, color_by: Union[str, int]) -> Tuple[np.ndarray, str]:
    """Per problem of ``codes.problem_ids``, the value it is coloured by, and its name: ``"problem"``
    (the ID) or the index of a problem feature (0: MetaBus's colored permutation)."""
    if color_by == "problem":
        return codes.problem_ids.copy(), "problem ID"
    d = codes.features.shape[1]
    if isinstance(color_by, bool) or not isinstance(color_by, (int, np.integer)) or not 0 <= color_by < d:
        raise ValueError(
            f"color_by={color_by!r} is not valid; accepted values: 'problem' or a feature index 0 .. {d - 1}"
        )
    names = FEATURE_NAMES.get(codes.family, ())
    name = names[color_by] if color_by < len(names) else f"problem feature {color_by}"
    return codes.features[:, color_by].copy(), name


def _stack(codes: DreamCodes, n_prefix_paths: int) -> Tuple[np.ndarray, List[Tuple[str, int, int, int]]]:
    """Every code drawn, stacked for one embedding, and what each row is: (kind, trial, problem, step)."""
    blocks = [codes.f, codes.g]
    what = [("f", -1, int(p), -1) for p in codes.problem_ids]
    what += [("g", k, int(p), len(codes.prefixes[k]) - 1) for k, p in enumerate(codes.trial_problem_ids)]
    for k in range(min(n_prefix_paths, len(codes.prefixes))):
        blocks.append(codes.prefixes[k])
        what += [("g_prefix", k, int(codes.trial_problem_ids[k]), t) for t in range(len(codes.prefixes[k]))]
    return np.concatenate(blocks), what


def code_rows(
    codes: DreamCodes, color_by: Union[str, int] = 0, method: str = "auto", n_prefix_paths: int = 3, seed: int = 0
) -> Tuple[List[Tuple[Any, ...]], str, str]:
    """The points :func:`code_figure` draws (:data:`CODE_COLUMNS`: kind "f", "g" or "g_prefix", the
    trial (-1 for f), the problem, the prefix's step (g: the exploration's length; f: -1), the colour's
    value and the 2-D position), the embedding used and the colour's name."""
    values, name = color_values(codes, color_by)
    value_of = dict(zip(codes.problem_ids.tolist(), values.tolist()))
    points, what = _stack(codes, n_prefix_paths)
    xy, used = embed_2d(points, method, seed)
    rows = [
        (kind, trial, pid, step, value_of[pid], round(float(x), 5), round(float(y), 5))
        for (kind, trial, pid, step), (x, y) in zip(what, xy)
    ]
    return rows, used, name


def code_figure(
    codes: DreamCodes,
    out: Optional[Union[str, pathlib.Path]] = None,
    color_by: Union[str, int] = 0,
    method: str = "auto",
    n_prefix_paths: int = 3,
    seed: int = 0,
    title: Optional[str] = None,
) -> Tuple[Any, List[Tuple[Any, ...]], str]:
    """Draw the codes in 2-D (see the module docstring): returns the figure, the rows of
    :func:`code_rows` and the embedding used; saved to ``out`` if given."""
    import matplotlib

    if out is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.lines import Line2D

    rows, used, name = code_rows(codes, color_by, method, n_prefix_paths, seed)
    kind = np.array([r[0] for r in rows])
    xy = np.array([(r[5], r[6]) for r in rows])
    value = np.array([r[4] for r in rows], dtype=float)
    levels = np.unique(value[kind == "f"])
    if len(levels) <= 60:  # a colour per value: tab20, tab20b, tab20c one after the other
        palette = [matplotlib.colormaps[m](i) for m in ("tab20", "tab20b", "tab20c") for i in range(20)]
        cmap = ListedColormap(palette[: len(levels)])
        index = {v: i for i, v in enumerate(levels)}
        value = np.array([index.get(v, 0) for v in value], dtype=float)
        norm = BoundaryNorm(np.arange(len(levels) + 1) - 0.5, len(levels))
    else:
        cmap, norm = matplotlib.colormaps["viridis"], None
    fig, ax = plt.subplots(figsize=(7.5, 6.2))
    f, g = kind == "f", kind == "g"
    dots = ax.scatter(*xy[f].T, c=value[f], cmap=cmap, norm=norm, s=28, alpha=0.75, edgecolors="none", zorder=2)
    ax.scatter(*xy[g].T, c=value[g], cmap=cmap, norm=norm, s=46, marker="x", linewidths=1.6, zorder=3)
    for k in range(min(n_prefix_paths, len(codes.prefixes))):
        path = xy[(kind == "g_prefix") & (np.array([r[1] for r in rows]) == k)]
        ax.plot(*path.T, "-", color="black", lw=0.9, alpha=0.8, zorder=4)
        ax.plot(*path[:-1].T, "o", ms=3, color="black", zorder=4)
        ax.plot(*path[0], "s", ms=7, mfc="white", mec="black", zorder=5)
    colorbar = fig.colorbar(dots, ax=ax, fraction=0.046, pad=0.03)
    colorbar.set_label(name, fontsize=8)
    if len(levels) <= 60:
        step = max(1, len(levels) // 12)
        colorbar.set_ticks(np.arange(0, len(levels), step))
        colorbar.set_ticklabels([str(int(v)) for v in levels[::step]])
    handles = [
        Line2D([], [], ls="none", marker="o", color="0.4", label=f"f(T), the {int(f.sum())} problems"),
        Line2D([], [], ls="none", marker="x", color="0.4", mew=1.6,
               label=f"g(tau^exp), {int(g.sum())} held-out trials"),
    ]  # fmt: skip
    if n_prefix_paths and codes.prefixes:
        handles.append(Line2D([], [], color="black", marker="o", ms=3,
                              label="g(tau_:t) step by step (square: t = 0)"))  # fmt: skip
    ax.legend(handles=handles, loc="best", fontsize=8)
    method_name = {"tsne": "t-SNE", "pca": "PCA"}[used]
    ax.set_xlabel(f"{method_name} 1")
    ax.set_ylabel(f"{method_name} 2")
    ax.set_title(title or f"DREAM's codes ({method_name}), coloured by {name}", fontsize=9)
    fig.tight_layout()
    if out is not None:
        fig.savefig(out, dpi=120, bbox_inches="tight")
        plt.close(fig)
    return fig, rows, used
