"""The paper's tabular example (Section 5.2, Figure 3, Appendix C.2): epsilon-greedy tabular
Q-learning versions of RL² and DREAM on MetaBandit-v0's rules, vectorised over seeds.

Setting (``MetaBandit-v0``): |A| actions, horizon H, N = |A|^H action sequences and as many
problems, drawn uniformly. Problem T rewards (with 1) only its own execution sequence a_T = T (digits
in base |A|). In the reward-free exploration episode the sequence a_* = (0, ..., 0) reveals T; every
other sequence a reveals nothing. As in Appendix C.2, a Q-value of a whole sequence stands for the
per-step Q-values (the state records the action history), and epsilon-greedy acts on sequences.

One *sample* is one trial: an exploration episode then an execution episode (2H steps).

* Execution (both methods): Q^exe(tau, a') is the sample mean of the rewards of playing a' after
  the exploration trajectory tau, where tau = (a, 0) for a != a_* and (a_*, T) for a_*.
  V^exe(tau) = max_a' Q^exe(tau, a').
* RL²: Q^exp(a) = V^exe(tau_a) for a != a_* (tau_a is deterministic) and, for a_*, the mean of
  V^exe((a_*, T)) over the problems T observed after a_* (current values, weighted by counts).
* DREAM: a count-based decoder q(T | tau); Q^exp(a) is the mean of log q(T | tau_a) over the
  observed (T, tau_a): for a != a_*, sum_T q log q (minus the entropy of the problems seen after
  a); for a_*, log 1 = 0. Unseen sequences have Q^exp = 0.

Q-values start at 0 and argmax ties are broken uniformly at random (a_* is action 0, which a
lowest-index tie-break would favour). The greedy exploration policy is *optimal* when
Q^exp(a_*) > Q^exp(a) for every a != a_*. The samples to learn it are 1 + the last trial after which
it was not optimal (measured after each trial's update); a run stops when every seed is optimal and
has been for at least the second half of the run (DREAM's optimality is then permanent, see
Proposition 1; RL²'s in practice), or at ``max_trials``; seeds not optimal then are reported as censored.

``python -m sb3_dream.tabular`` writes, under ``--out``: ``fig3a_samples.csv`` / ``fig3a.png``
(samples to learn the optimal exploration policy against |A|, ``--seeds`` seeds) and
``fig3bcd_curves.csv`` / ``fig3bcd.png`` (exploration Q-values, V^exe(tau_*) averaged over T, and the
greedy policies' expected execution return over training for |A| = ``--curve-actions``,
``--curve-seeds`` seeds).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import time
from typing import Dict, List, Optional, Sequence

import numpy as np

from dream_envs.checks import check_choice, check_positive_int

METHODS = ("rl2", "dream")
LABELS = {"rl2": "RL²", "dream": "DREAM"}


class TabularMetaLearner:
    """All seeds' tables of one method as arrays with a leading seed axis; :meth:`step` plays one
    trial in every seed and applies the update."""

    def __init__(self, method: str, n_actions: int, horizon: int, n_seeds: int, epsilon: float, seed: int) -> None:
        check_choice("method", method, METHODS)
        if not 0.0 <= epsilon <= 1.0:
            raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}")
        # the bandit needs an action besides the revealing one a_*
        n_actions, horizon = check_positive_int("n_actions", n_actions, 2), check_positive_int("horizon", horizon)
        self.method, self.epsilon = method, float(epsilon)
        self.n = n = n_actions**horizon  # sequences = problems
        self.n_seeds = s = check_positive_int("n_seeds", n_seeds)
        self.rng = np.random.default_rng(seed)
        self.rows = np.arange(s)
        # tau index: a for a != a_* (= 0), n + T for (a_*, T).
        self.exe_sum = np.zeros((s, 2 * n, n))
        self.exe_cnt = np.zeros((s, 2 * n, n))
        self.value = np.zeros((s, 2 * n))  # V^exe(tau)
        self.star_cnt = np.zeros((s, n))  # problems observed after a_*
        self.dec_cnt = np.zeros((s, n, n))  # DREAM: counts of T after tau_a (rows a != 0 used)
        self.dec_q = np.zeros((s, n))  # DREAM: mean log q(T | tau_a)
        self.trials = 0

    def q_exp(self) -> np.ndarray:
        """``[seeds, N]``: the exploration Q-values."""
        if self.method == "dream":
            return self.dec_q.copy()  # column 0 (a_*) stays 0 = log 1
        q = self.value[:, : self.n].copy()
        total = self.star_cnt.sum(1)
        weighted = (self.star_cnt * self.value[:, self.n :]).sum(1)
        q[:, 0] = np.where(total > 0, weighted / np.maximum(total, 1), 0.0)
        return q

    def exploration_optimal(self, q: Optional[np.ndarray] = None) -> np.ndarray:
        q = self.q_exp() if q is None else q
        return q[:, 0] > q[:, 1:].max(1)

    def _act(self, q: np.ndarray) -> np.ndarray:
        greedy = np.argmax(q + 1e-12 * self.rng.random(q.shape), axis=1)  # ties broken at random
        explore = self.rng.random(self.n_seeds) < self.epsilon
        return np.where(explore, self.rng.integers(self.n, size=self.n_seeds), greedy)

    def step(self) -> None:
        n, rows = self.n, self.rows
        problem = self.rng.integers(n, size=self.n_seeds)
        a = self._act(self.q_exp())
        tau = np.where(a == 0, n + problem, a)
        cnt = self.exe_cnt[rows, tau]
        a2 = self._act(self.exe_sum[rows, tau] / np.maximum(cnt, 1))
        reward = (a2 == problem).astype(float)
        self.exe_sum[rows, tau, a2] += reward
        self.exe_cnt[rows, tau, a2] += 1
        self.value[rows, tau] = (self.exe_sum[rows, tau] / np.maximum(self.exe_cnt[rows, tau], 1)).max(1)
        star = a == 0
        self.star_cnt[rows[star], problem[star]] += 1
        if self.method == "dream":
            other = ~star
            r, act = rows[other], a[other]
            self.dec_cnt[r, act, problem[other]] += 1
            counts = self.dec_cnt[r, act]
            p = counts / counts.sum(1, keepdims=True)
            self.dec_q[r, act] = (p * np.log(np.where(p > 0, p, 1.0))).sum(1)
        self.trials += 1

    def v_star(self) -> np.ndarray:
        """``[seeds]``: V^exe((a_*, T)) averaged over the problems T (Figure 3c)."""
        return self.value[:, self.n :].mean(1)

    def greedy_return(self) -> np.ndarray:
        """``[seeds]``: the expected execution return of the greedy policies (ties uniform)."""
        n, q = self.n, self.q_exp()
        top = np.isclose(q, q.max(1, keepdims=True), rtol=0, atol=1e-12)
        p_star = top[:, 0] / top.sum(1)
        mean = self.exe_sum[:, n:] / np.maximum(self.exe_cnt[:, n:], 1)  # [S, T, a']
        best = np.isclose(mean, mean.max(2, keepdims=True), rtol=0, atol=1e-12)
        right = best[:, np.arange(n), np.arange(n)] / best.sum(2)  # P(greedy plays a_T | (a_*, T))
        return p_star * right.mean(1) + (1 - p_star) / n


def samples_to_learn(
    method: str,
    n_actions: int,
    n_seeds: int,
    horizon: int = 1,
    epsilon: float = 0.1,
    seed: int = 0,
    max_trials: int = 1_000_000,
    check_every: int = 1000,
) -> Dict[str, np.ndarray]:
    """Samples (trials) each seed needs for its greedy exploration policy to become optimal for good
    (see the module docstring): ``{"samples": [seeds], "censored": [seeds] bool}``."""
    learner = TabularMetaLearner(method, n_actions, horizon, n_seeds, epsilon, seed)
    last_bad = np.full(n_seeds, -1)
    while learner.trials < max_trials:
        for _ in range(check_every):
            learner.step()
            bad = ~learner.exploration_optimal()
            last_bad[bad] = learner.trials - 1
        if not bad.any() and (last_bad < learner.trials // 2).all():
            break
    censored = ~learner.exploration_optimal()
    return {"samples": last_bad + 2, "censored": censored, "trials_run": np.array(learner.trials)}


def training_curves(
    n_actions: int = 8,
    n_seeds: int = 3,
    horizon: int = 1,
    epsilon: float = 0.1,
    n_trials: int = 20_000,
    n_records: int = 400,
    seed: int = 0,
) -> List[dict]:
    """Rows of Figure 3b-d: for each method, seed and recorded trial (about ``n_records``, spaced
    evenly on a log scale, every trial at first), Q^exp of every sequence, V^exe(tau_*) averaged
    over T, the greedy expected return and whether exploration is optimal."""
    rows = []
    record = set(np.unique(np.geomspace(1, n_trials + 1, n_records).astype(int) - 1).tolist())
    for m, method in enumerate(METHODS):
        learner = TabularMetaLearner(method, n_actions, horizon, n_seeds, epsilon, seed + m)
        for t in range(n_trials + 1):
            if t in record:
                q, v, ret = learner.q_exp(), learner.v_star(), learner.greedy_return()
                optimal = learner.exploration_optimal(q)
                for s in range(n_seeds):
                    row = {"method": method, "seed": s, "trial": t, "v_star": v[s], "return": ret[s]}
                    row["optimal"] = int(optimal[s])
                    row.update({f"q{a}": q[s, a] for a in range(learner.n)})
                    rows.append(row)
            if t < n_trials:
                learner.step()
    return rows


def _write_csv(path: str, rows: Sequence[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _first_stable(trials: np.ndarray, optimal: np.ndarray) -> Optional[int]:
    """The first recorded trial from which exploration stays optimal to the end, or None."""
    bad = np.flatnonzero(~optimal.astype(bool))
    if len(bad) == 0:
        return int(trials[0])
    return None if bad[-1] + 1 >= len(trials) else int(trials[bad[-1] + 1])


def plot_samples(rows: Sequence[dict], path: str, horizon: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    for method in METHODS:
        mine = [r for r in rows if r["method"] == method]
        x = [r["n_actions"] for r in mine]
        y = np.array([r["mean"] for r in mine])
        err = np.array([r["stderr"] for r in mine])
        ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=LABELS[method])
    ax.set_yscale("log")
    ax.set_xlabel("|A|")
    ax.set_ylabel("samples to learn optimal exploration")
    ax.set_title(f"(a) sample complexity (H = {horizon}, {rows[0]['seeds']} seeds)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_curves(rows: Sequence[dict], path: str, n_actions: int, horizon: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = n_actions**horizon
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.6))
    colors = {"rl2": "tab:blue", "dream": "tab:orange"}
    for method in METHODS:
        seeds = sorted({r["seed"] for r in rows if r["method"] == method})
        for s in seeds:
            mine = [r for r in rows if r["method"] == method and r["seed"] == s]
            t = np.array([r["trial"] for r in mine])
            optimal = np.array([r["optimal"] for r in mine])
            at = _first_stable(t, optimal)
            ax = axes[0] if method == "rl2" else axes[1]
            q = np.array([[r[f"q{a}"] for a in range(n)] for r in mine])
            ax.plot(t, q[:, 1:].max(1), color="gray", lw=1, alpha=0.7, label="max over a ≠ a*" if s == 0 else None)
            ax.plot(t, q[:, 0], color=colors[method], lw=1.5, label="a*" if s == 0 else None)
            series = {2: [r["v_star"] for r in mine], 3: [r["return"] for r in mine]}
            for k, y in series.items():
                axes[k].plot(t, y, color=colors[method], lw=1.2, label=LABELS[method] if s == 0 else None)
            if at is not None:
                i = int(np.searchsorted(t, at))
                ax.plot(t[i], q[i, 0], "ko", ms=5)
                for k, y in series.items():
                    axes[k].plot(t[i], y[i], "ko", ms=5)
    axes[0].set_title("(b) RL² exploration Q-values")
    axes[1].set_title("(b) DREAM exploration Q-values")
    axes[2].set_title("(c) V^exe(τ*) (mean over problems)")
    axes[3].set_title("(d) expected return (greedy)")
    for ax in axes:
        ax.set_xscale("symlog", linthresh=10)
        ax.set_xlabel("samples (trials)")
        ax.legend(fontsize=8)
    fig.suptitle(f"Tabular example, |A| = {n_actions}, H = {horizon}; dot: exploration optimal from here on")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_dream.tabular", description=__doc__.split("\n\n")[0])
    parser.add_argument("--actions", type=int, nargs="+", default=[2, 3, 4, 5, 6, 7, 8], help="|A| values of Fig. 3a")
    parser.add_argument("--seeds", type=int, default=1000, help="seeds per |A| in Fig. 3a")
    parser.add_argument("--horizon", type=int, default=1, help="H")
    parser.add_argument("--epsilon", type=float, default=0.1, help="epsilon of epsilon-greedy")
    parser.add_argument("--max-trials", type=int, default=1_000_000, help="cap on trials per run of Fig. 3a")
    parser.add_argument("--curve-actions", type=int, default=8, help="|A| of Fig. 3b-d")
    parser.add_argument("--curve-seeds", type=int, default=3, help="seeds of Fig. 3b-d")
    parser.add_argument("--curve-trials", type=int, default=20_000, help="trials of Fig. 3b-d")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/tabular", help="output folder")
    parser.add_argument("--skip-curves", action="store_true", help="only Fig. 3a")
    parser.add_argument("--skip-samples", action="store_true", help="only Fig. 3b-d")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)

    if not args.skip_samples:
        _figure_3a(args)
    if not args.skip_curves:
        start = time.perf_counter()
        curves = training_curves(
            args.curve_actions, args.curve_seeds, args.horizon, args.epsilon, args.curve_trials, seed=args.seed
        )
        _write_csv(os.path.join(args.out, "fig3bcd_curves.csv"), curves)
        plot_curves(curves, os.path.join(args.out, "fig3bcd.png"), args.curve_actions, args.horizon)
        print(f"Figure 3b-d: {time.perf_counter() - start:.1f} s")


def _figure_3a(args: argparse.Namespace) -> None:
    rows = []
    start = time.perf_counter()
    for n_actions in args.actions:
        for m, method in enumerate(METHODS):
            t0 = time.perf_counter()
            res = samples_to_learn(
                method, n_actions, args.seeds, args.horizon, args.epsilon, args.seed + 1000 * n_actions + m,
                max_trials=args.max_trials,
            )  # fmt: skip
            samples = res["samples"].astype(float)
            rows.append(
                {
                    "method": method,
                    "n_actions": n_actions,
                    "horizon": args.horizon,
                    "epsilon": args.epsilon,
                    "seeds": args.seeds,
                    "mean": samples.mean(),
                    "stderr": samples.std(ddof=1) / math.sqrt(len(samples)) if len(samples) > 1 else 0.0,
                    "median": float(np.median(samples)),
                    "censored": int(res["censored"].sum()),
                    "trials_run": int(res["trials_run"]),
                    "seconds": round(time.perf_counter() - t0, 2),
                }
            )
            print(", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in rows[-1].items()))
    for n_actions in args.actions:
        rl2, dream = (next(r for r in rows if r["method"] == m and r["n_actions"] == n_actions) for m in METHODS)
        ratio = rl2["mean"] / dream["mean"]
        bound = n_actions**args.horizon / (args.horizon * math.log(n_actions))
        print(f"|A|={n_actions}: RL²/DREAM = {ratio:.2f} (|A|^H / (H log |A|) = {bound:.2f})")
        rl2["ratio_rl2_over_dream"] = dream["ratio_rl2_over_dream"] = ratio
    _write_csv(os.path.join(args.out, "fig3a_samples.csv"), rows)
    plot_samples(rows, os.path.join(args.out, "fig3a.png"), args.horizon)
    print(f"Figure 3a: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
