"""One Optuna study searched by two ``sb3-dream-zoo train --optimize`` processes, then its best trial trained."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("rl_zoo3")
optuna = pytest.importorskip("optuna")

from sb3_dream.dream import DREAM  # noqa: E402
from sb3_dream.zoo.cli import main  # noqa: E402
from sb3_dream.zoo.hyperparams_opt import EXECUTION_BODIES  # noqa: E402

TINY = ["-params", "buffer_size:100", "execution_buffer_size:200"]


def test_two_workers_share_one_sqlite_study_and_its_best_trial_trains(tmp_path):
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    common = ["--algo", "dream", "--env", "MetaBandit-v0", "--storage", storage, "--study-name", "bandit"]
    optimize = [
        "--optimize", "--n-trials", "2", "-n", "100", "--n-evaluations", "1", "--eval-episodes", "4",
        "--no-optim-plots", "--num-threads", "1", "--sampler", "random", "--pruner", "none",
    ]  # fmt: skip
    workers = [
        subprocess.Popen(
            [sys.executable, "-m", "sb3_dream.zoo", "train", *common, *optimize, "--seed", str(k),
             "-f", str(tmp_path / f"logs{k}"), *TINY],  # fmt: skip
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for k in range(2)
    ]
    outputs = [worker.communicate(timeout=300)[0] for worker in workers]
    assert [w.returncode for w in workers] == [0, 0], outputs
    study = optuna.load_study(study_name="bandit", storage=storage)
    trials = study.get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 4  # two from each worker, in one study
    assert all(0.0 <= t.value <= 1.0 for t in trials)  # the held-out meta-test return, a success rate here
    assert {"execution_body", "reward_penalty", "execution_sampling", "eps_decay_steps"} <= set(trials[0].params)

    best = study.best_trial
    logs = tmp_path / "best"
    main(["train", *common, "--best-trial", "-n", "50", "--seed", "0", "--num-threads", "1", "-f", str(logs), *TINY])
    model = DREAM.load(logs / "dream" / "MetaBandit-v0_1" / "MetaBandit-v0.zip")
    assert model.reward_penalty == pytest.approx(best.params["reward_penalty"])
    assert model.lr_schedule(1.0) == pytest.approx(best.params["learning_rate"])
    assert model.execution_sampling == best.params["execution_sampling"] and model.buffer_size == 100
    assert model.policy.execution_hidden_sizes == EXECUTION_BODIES[best.params["execution_body"]]
    with pytest.raises(SystemExit, match="--best-trial trains with a study's best trial"):
        main(["train", "--algo", "dream", "--env", "MetaBandit-v0", "--best-trial"])


def test_best_trial_becomes_params_and_the_command_s_own_params_win(tmp_path):
    from optuna.distributions import CategoricalDistribution, FloatDistribution

    from sb3_dream.zoo import register
    from sb3_dream.zoo.cli import best_trial_args

    register()
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    study = optuna.create_study(storage=storage, study_name="s", direction="maximize")
    distributions = {
        "learning_rate": FloatDistribution(1e-5, 1e-3, log=True),
        "execution_body": CategoricalDistribution(list(EXECUTION_BODIES)),
    }
    for value, lr in ((0.9, 1e-4), (0.2, 1e-3)):  # the best is trial 0
        params = {"learning_rate": lr, "execution_body": "128x128"}
        study.add_trial(optuna.trial.create_trial(params=params, distributions=distributions, value=value))
    argv = ["--algo", "dream", "--storage", storage, "--study-name", "s", "-params", "execution_body_unused:1",
            "learning_rate:5e-4", "-n", "10"]  # fmt: skip
    assert best_trial_args(argv) == [
        "--algo", "dream", "--storage", storage, "--study-name", "s", "-n", "10", "-params",
        "learning_rate:5e-4", "policy_kwargs:{'execution_hidden_sizes': (128, 128)}", "execution_body_unused:1",
    ]  # fmt: skip


def test_trials_report_and_are_pruned_on_the_held_out_meta_test_return(monkeypatch):
    import rl_zoo3.exp_manager
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_dream.evaluation import evaluate_meta
    from sb3_dream.zoo import register

    register()
    register()  # idempotent: the callback is wrapped once
    callback_class = rl_zoo3.exp_manager.TrialEvalCallback
    assert callback_class.meta_test and callback_class.__mro__[1].__name__ == "TrialEvalCallback"
    study = optuna.create_study(direction="maximize")
    trial = study.ask()
    model = DREAM("MetaBandit-v0", buffer_size=50, execution_buffer_size=100, seed=0)
    eval_env = make_vec_env("MetaBandit-v0", n_envs=1, env_kwargs={"split": "test"})  # as the zoo makes it
    callback = callback_class(eval_env, trial, n_eval_episodes=8, eval_freq=1)
    callback.init_callback(model)
    calls = []

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return evaluate_meta(*args, **kwargs)

    monkeypatch.setattr("sb3_dream.evaluation.evaluate_meta", spy)
    assert callback.on_step()
    assert [(c["split"], c["n_trials"]) for c in calls] == [("test", 8)]
    expected = evaluate_meta(model, "MetaBandit-v0", n_trials=8, split="test").mean
    assert callback.last_mean_reward == pytest.approx(expected)
    assert study.trials[0].intermediate_values == {1: pytest.approx(expected)}
