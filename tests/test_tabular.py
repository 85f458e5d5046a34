"""The tabular example (Figure 3): update rules on hand cases, the ordering of RL² and DREAM, the CLI."""

import csv

import numpy as np
import pytest

from sb3_dream import tabular
from sb3_dream.tabular import TabularMetaLearner, samples_to_learn


def test_dream_exploration_values_by_hand():
    # |A| = 3: after seeing problems 0 and 1 once each behind sequence 1, Q(1) = log(1/2); sequence 2
    # unseen keeps 0, so a_* (Q = 0 = log 1) is not yet strictly best (Proposition 1's condition).
    learner = TabularMetaLearner("dream", 3, 1, n_seeds=1, epsilon=0.0, seed=0)
    learner.dec_cnt[0, 1, [0, 1]] = 1
    learner.dec_q[0, 1] = np.log(0.5)
    assert learner.q_exp()[0] == pytest.approx([0.0, np.log(0.5), 0.0])
    assert not learner.exploration_optimal()[0]
    learner.dec_q[0, 2] = np.log(0.5)
    assert learner.exploration_optimal()[0]


def test_rl2_exploration_values_by_hand():
    # Q(a_*) is the count-weighted mean of V^exe((a_*, T)) over the problems seen after a_*.
    learner = TabularMetaLearner("rl2", 2, 1, n_seeds=1, epsilon=0.0, seed=0)
    learner.value[0] = [0.0, 0.3, 1.0, 0.0]  # tau: -, (1, 0), (a_*, 0), (a_*, 1)
    learner.star_cnt[0] = [3, 1]
    assert learner.q_exp()[0] == pytest.approx([0.75, 0.3])
    assert learner.exploration_optimal()[0]


def test_learning_reaches_the_optimal_policy():
    for method in tabular.METHODS:
        learner = TabularMetaLearner(method, 3, 1, n_seeds=20, epsilon=0.2, seed=1)
        for _ in range(3000):
            learner.step()
        assert learner.exploration_optimal().all()
        assert learner.greedy_return() == pytest.approx(np.ones(20))
        assert learner.v_star() == pytest.approx(np.ones(20))


def test_dream_needs_fewer_samples_than_rl2_at_8_actions():
    # 100 seeds each: DREAM ~20 trials, RL² thousands (docs/baselines.md has the 1000-seed numbers).
    dream = samples_to_learn("dream", 8, 100, seed=1)
    rl2 = samples_to_learn("rl2", 8, 100, seed=2, max_trials=300_000)
    assert not dream["censored"].any()
    d, r = dream["samples"], rl2["samples"]
    stderr = np.hypot(d.std(ddof=1), r.std(ddof=1)) / np.sqrt(100)
    assert r.mean() - d.mean() > 10 * stderr
    assert np.median(r) > 10 * np.median(d)


def test_cli_writes_figures(tmp_path):
    tabular.main(["--actions", "2", "3", "--seeds", "20", "--curve-actions", "3", "--curve-trials", "300",
                  "--out", str(tmp_path)])  # fmt: skip
    for name in ("fig3a_samples.csv", "fig3a.png", "fig3bcd_curves.csv", "fig3bcd.png"):
        assert (tmp_path / name).stat().st_size > 0
    with open(tmp_path / "fig3a_samples.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["method"], r["n_actions"]) for r in rows] == [("rl2", "2"), ("dream", "2"), ("rl2", "3"), ("dream", "3")]
    assert all(float(r["ratio_rl2_over_dream"]) > 1 for r in rows)


@pytest.mark.parametrize(
    "name, value",
    [("method", "ppo"), ("n_actions", 1), ("horizon", 0), ("n_seeds", 0), ("epsilon", 1.5)],
)
def test_bad_arguments_name_themselves(name, value):
    kwargs = dict(method="dream", n_actions=4, horizon=1, n_seeds=2, epsilon=0.1, seed=0)
    with pytest.raises(ValueError, match=name):
        TabularMetaLearner(**{**kwargs, name: value})
