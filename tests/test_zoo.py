"""sb3_dream.zoo: rl-zoo3's tables, the packaged hyperparameters (checked against sb3_dream.presets), the
CLI's defaults, train/enjoy/optimize."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest

rl_zoo3 = pytest.importorskip("rl_zoo3")
yaml = pytest.importorskip("yaml")
optuna = pytest.importorskip("optuna")

from sb3_dream.dream import DREAM  # noqa: E402
from sb3_dream.rl2dqn import RL2DQN  # noqa: E402
from sb3_dream.import_dqn import IMPORT  # noqa: E402
from sb3_dream.presets import IMPORT_PRESETS, PRESETS, RL2DQN_PRESETS, VARIBAD_PRESETS  # noqa: E402
from sb3_dream.varibad import VariBAD  # noqa: E402
from sb3_dream.zoo import (  # noqa: E402
    LAPTOP_ALGOS,
    MEASURED_ALGOS,
    SETTINGS,
    ZOO_ALGOS,
    algorithms,
    hyperparams_path,
    register,
)
from sb3_dream.zoo.cli import enjoy_args, main, train_args  # noqa: E402
from sb3_dream.zoo.hyperparams_opt import CONVERTERS, SAMPLERS  # noqa: E402

ENVS = ("MetaBus-v0", "MetaCook-v0", "SignNav3D-v0", "MetaBandit-v0")
# Constructor arguments that are not hyperparameters (rl-zoo3 passes env, seed, verbose, device).
NOT_HYPERPARAMETERS = {
    "self",
    "policy",
    "env",
    "stats_window_size",
    "tensorboard_log",
    "policy_kwargs",
    "verbose",
    "seed",
    "device",
    "parallel_updates",  # like device: how the updates run, not what they compute
    "_init_setup_model",
    "replay_buffer_class",
    "replay_buffer_kwargs",
}
# The paper's smaller buffers for the 3D env (Appendix B.4) and RL2DQN's image policy there.
PAPER_3D = {
    "dream": {"buffer_size": 10_000, "execution_buffer_size": 60_000},
    "rl2_dqn": {"buffer_size": 10_000},
    "import_dqn": {"buffer_size": 10_000},
    "varibad": {"buffer_size": 10_000},
}
POLICIES = {
    "dream": {},
    "rl2_dqn": {"SignNav3D-v0": "CnnLstmPolicy"},
    "import_dqn": {"SignNav3D-v0": "CnnLstmPolicy"},
    "varibad": {"SignNav3D-v0": "CnnLstmPolicy"},
}
# The one source of named presets, per zoo algorithm: the packaged files must agree with it.
ZOO_PRESETS = {"dream": PRESETS, "rl2_dqn": RL2DQN_PRESETS, "import_dqn": IMPORT_PRESETS, "varibad": VARIBAD_PRESETS}
TINY = {
    "dream": [
        "exploration_learning_starts:5",
        "execution_learning_starts:5",
        "buffer_size:200",
        "execution_buffer_size:1000",
    ],
    "rl2_dqn": ["learning_starts:50", "buffer_size:200"],
    "import_dqn": ["learning_starts:50", "buffer_size:200"],
    "varibad": ["learning_starts:50", "buffer_size:200"],
}


def test_register_fills_rl_zoo3_tables():
    register()
    register()  # idempotent
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER

    assert rl_zoo3.ALGOS["dream"] is DREAM and rl_zoo3.ALGOS["rl2_dqn"] is RL2DQN
    assert rl_zoo3.ALGOS["import_dqn"] is IMPORT and rl_zoo3.ALGOS["varibad"] is VariBAD
    assert rl_zoo3.ALGOS["ppo"].__name__ == "PPO"  # the zoo's own algorithms stay
    for algo in ZOO_ALGOS:
        assert HYPERPARAMS_SAMPLER[algo] is SAMPLERS[algo] and HYPERPARAMS_CONVERTER[algo] is CONVERTERS[algo]
    import gymnasium as gym

    for env_id in ENVS:
        assert env_id in gym.registry


@pytest.mark.parametrize("algo", ZOO_ALGOS)
def test_packaged_hyperparameters_are_the_paper_preset_for_every_env(algo):
    cls = algorithms()[algo]
    defaults = {
        name: p.default
        for name, p in inspect.signature(cls.__init__).parameters.items()
        if name not in NOT_HYPERPARAMETERS and p.kind is not p.VAR_KEYWORD  # **sb3_kwargs: SB3's names it rejects
    }
    default_policy = inspect.signature(cls.__init__).parameters["policy"].default
    config = yaml.safe_load(hyperparams_path(algo).read_text())
    assert set(config) == set(ENVS)
    for env_id, params in config.items():
        assert params["n_envs"] == 1 and params["n_timesteps"] > 0
        assert params["policy"] == POLICIES[algo].get(env_id, default_policy), env_id
        hyper = {k: v for k, v in params.items() if k not in ("n_timesteps", "n_envs", "policy")}
        assert set(hyper) == set(defaults), f"{algo} {env_id}: listed {sorted(hyper)} vs constructor {sorted(defaults)}"
        expected = {**defaults, **ZOO_PRESETS[algo]["paper"], **(PAPER_3D[algo] if env_id == "SignNav3D-v0" else {})}
        assert hyper == expected, env_id


ZOO_KEYS = {"n_timesteps", "n_envs", "policy", "policy_kwargs"}


@pytest.mark.parametrize("algo", MEASURED_ALGOS)
def test_measured_settings_are_the_fast_preset_and_valid_arguments(algo):
    cls = algorithms()[algo]
    arguments = set(inspect.signature(cls.__init__).parameters)
    config = yaml.safe_load(hyperparams_path(algo, "measured").read_text())
    assert set(config) == set(ENVS)
    for env_id in ("MetaBus-v0", "MetaCook-v0"):  # the envs of the README's measured runs
        params = config[env_id]
        assert params["n_envs"] == 4 and params["n_timesteps"] >= 6e5
        fast = ZOO_PRESETS[algo]["fast"]  # the schedules of the README's measured runs (the runner's --preset fast)
        assert {k: params[k] for k in fast} == fast, env_id
        hyper = {k: v for k, v in params.items() if k not in ZOO_KEYS}
        assert set(hyper) <= arguments, env_id
        policy_kwargs = eval(params.get("policy_kwargs", "dict()"))  # as rl-zoo3 reads it
        small = {"buffer_size": 50, **({"execution_buffer_size": 100} if algo == "dream" else {})}
        model = cls(params["policy"], env_id, policy_kwargs=policy_kwargs, **{**hyper, **small})
        for key, value in hyper.items():
            assert getattr(model, key) == value, (env_id, key)
    assert config["SignNav3D-v0"]["policy"] == POLICIES[algo].get("SignNav3D-v0", "DreamPolicy")
    accepted = "accepted values: 'paper', 'measured', 'laptop'"
    with pytest.raises(ValueError, match=f"settings='fast' is not valid; {accepted}"):
        hyperparams_path(algo, "fast")


def test_laptop_settings_are_the_laptop_preset():
    # rl-zoo3 reads policy_kwargs as a Python expression and everything else as YAML values
    config = yaml.safe_load(hyperparams_path("dream", "laptop").read_text())
    assert LAPTOP_ALGOS == ("dream",) and set(config) == {"MetaBus-v0", "MetaCook-v0"}
    for env_id, params in config.items():
        assert params["n_envs"] == 4 and params["policy"] == "DreamPolicy"
        hyper = {k: v for k, v in params.items() if k not in ZOO_KEYS}
        assert {**hyper, "policy_kwargs": eval(params["policy_kwargs"])} == PRESETS["laptop"], env_id
        model = DREAM(params["policy"], env_id, buffer_size=50, execution_buffer_size=100, **PRESETS["laptop"])
        assert model.execution_sampling == "episodes"
    for algo in sorted(set(ZOO_ALGOS) - set(LAPTOP_ALGOS)):
        with pytest.raises(ValueError, match=f"algo='{algo}' has no 'laptop' settings"):
            hyperparams_path(algo, "laptop")


def test_every_algorithm_ships_measured_settings_and_the_baselines_share_rl2s_schedules():
    # the README's rows of every algorithm come from measured runs; the runner's --preset fast
    # gave IMPORT and VARIBAD RL2DQN's schedules, so their files must say the same
    assert set(MEASURED_ALGOS) == set(ZOO_ALGOS)
    for algo in ("import_dqn", "varibad"):
        assert ZOO_PRESETS[algo]["fast"] == RL2DQN_PRESETS["fast"]
        rl2, own = (yaml.safe_load(hyperparams_path(a, "measured").read_text()) for a in ("rl2_dqn", algo))
        assert own == rl2, algo
        assert train_args(["--algo", algo, "--settings", "measured"])[:2] == [
            "--conf-file",
            str(hyperparams_path(algo, "measured")),
        ]


def test_cli_settings_picks_the_packaged_file():
    args = train_args(["--algo", "dream", "--env", "MetaCook-v0", "--settings", "measured", "-n", "5"])
    assert args[:2] == ["--conf-file", str(hyperparams_path("dream", "measured"))]
    assert "--settings" not in args and args[-2:] == ["-n", "5"]  # rl-zoo3 never sees the flag
    paper = train_args(["--algo", "rl2_dqn", "--settings=paper"])
    assert paper[:2] == ["--conf-file", str(hyperparams_path("rl2_dqn"))]
    with pytest.raises(SystemExit, match="settings='fast' is not valid; accepted values: paper, measured, laptop"):
        train_args(["--algo", "dream", "--settings", "fast"])
    with pytest.raises(SystemExit, match="--settings picks the packaged --conf-file"):
        train_args(["--algo", "dream", "--settings", "measured", "--conf-file", "my.yml"])
    assert SETTINGS == ("paper", "measured", "laptop")
    laptop = train_args(["--algo", "dream", "--settings", "laptop"])
    assert laptop[:2] == ["--conf-file", str(hyperparams_path("dream", "laptop"))]
    with pytest.raises(SystemExit, match="algo='rl2_dqn' has no 'laptop' settings"):
        train_args(["--algo", "rl2_dqn", "--settings", "laptop"])


def test_cli_defaults_put_first_so_user_flags_win():
    args = train_args(["--algo", "dream", "--env", "MetaBus-v0", "--env-kwargs", "variant:'map'", "split:'all'"])
    assert args[:2] == ["--conf-file", str(hyperparams_path("dream"))]
    # the zoo's evaluation runs on the held-out problems, with the same env arguments
    assert args[2:5] == ["--eval-env-kwargs", "variant:'map'", "split:'test'"]
    assert args[5:] == ["--algo", "dream", "--env", "MetaBus-v0", "--env-kwargs", "variant:'map'", "split:'all'"]
    mine = ["--algo", "rl2_dqn", "--env", "MetaBus-v0", "--conf-file", "my.yml", "--eval-env-kwargs", "split:'train'"]
    assert train_args(mine) == mine
    assert train_args(["--algo", "ppo", "--env", "CartPole-v1"]) == ["--algo", "ppo", "--env", "CartPole-v1"]

    args = enjoy_args(["--algo", "dream", "--env", "MetaBus-v0"])
    assert args[:3] == ["--folder", "logs", "--no-render"]  # trial envs render rgb_array only
    mine = ["--algo", "dream", "--env", "MetaBus-v0", "-f", "x", "--no-render"]
    assert enjoy_args(mine) == mine


def test_cli_rejects_unknown_commands():
    with pytest.raises(SystemExit, match="command='fit' is not valid"):
        main(["fit", "--algo", "dream"])


@pytest.mark.parametrize("algo", ZOO_ALGOS)
def test_samplers_give_valid_constructor_arguments(algo):
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    trial = study.ask()
    kwargs = SAMPLERS[algo](trial, 0, 1, {"using_her_replay_buffer": False, "her_kwargs": {}})
    assert CONVERTERS[algo](trial.params) == kwargs
    small = {"buffer_size": 50, **({"execution_buffer_size": 100} if algo == "dream" else {})}
    model = algorithms()[algo]("MetaBandit-v0", **{**kwargs, **small})
    for key, value in kwargs.items():
        if key == "policy_kwargs":  # DREAM's execution body
            assert model.policy.execution_hidden_sizes == value["execution_hidden_sizes"]
        else:
            assert getattr(model, key) == value


@pytest.mark.parametrize("algo", ZOO_ALGOS)
def test_zoo_train_then_enjoy(algo, tmp_path, capsys):
    logs = tmp_path / "logs"
    main(
        ["train", "--algo", algo, "--env", "MetaBus-v0", "-n", "240", "--eval-freq", "120", "--eval-episodes", "2",
         "--seed", "0", "--num-threads", "1", "-f", str(logs), "-params", *TINY[algo]]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert str(hyperparams_path(algo)) in out and "eval_env_kwargs={'split': 'test'}" in out
    run = logs / algo / "MetaBus-v0_1"
    assert (run / "MetaBus-v0.zip").exists() and (run / "evaluations.npz").exists()
    assert algorithms()[algo].load(run / "MetaBus-v0.zip").num_timesteps == 240

    # enjoy in a fresh interpreter: the names resolve through ``python -m sb3_dream.zoo`` alone
    enjoy = subprocess.run(
        [sys.executable, "-m", "sb3_dream.zoo", "enjoy", "--algo", algo, "--env", "MetaBus-v0", "-f", str(logs),
         "-n", "90", "--deterministic", "--num-threads", "1"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert enjoy.returncode == 0, enjoy.stderr
    # whole trials (exploration + execution) ran through predict(state, episode_start)
    assert "adding --no-render" in enjoy.stdout and "Mean reward:" in enjoy.stdout
    assert enjoy.stdout.count("Episode Reward:") >= 2


def test_zoo_trains_with_the_measured_settings(tmp_path, capsys):
    logs = tmp_path / "logs"
    main(
        ["train", "--algo", "dream", "--env", "MetaCook-v0", "--settings", "measured", "-n", "240",
         "--seed", "0", "--num-threads", "1", "-f", str(logs), "-params", *TINY["dream"]]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert str(hyperparams_path("dream", "measured")) in out and "('n_envs', 4)" in out
    model = DREAM.load(logs / "dream" / "MetaCook-v0_1" / "MetaCook-v0.zip")
    assert model.n_envs == 4 and model.reward_penalty == 0.01 and model.eps_decay_steps == 30_000
    assert model.policy.execution_hidden_sizes == (256, 256) and not model.policy.execution_instruction_mlp


def test_zoo_optimize_runs_trials_with_the_dream_sampler(tmp_path, capsys):
    logs = tmp_path / "logs"
    main(
        ["train", "--algo", "dream", "--env", "MetaBandit-v0", "-optimize", "--n-trials", "2", "-n", "100",
         "--n-evaluations", "1", "--eval-episodes", "2", "--no-optim-plots", "--seed", "0", "--num-threads", "1",
         "-f", str(logs), "-params", "buffer_size:100", "execution_buffer_size:200"]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert "Number of finished trials:  2" in out and "exploration_learning_starts" in out
    assert list((logs / "dream").glob("report_MetaBandit-v0_2-trials-100-*.csv"))


def test_zoo_trains_dream_with_sb3s_learning_starts(tmp_path, capsys):
    """``-params learning_starts:N``, SB3's usual way to set when updates begin, reaches DREAM."""
    logs = tmp_path / "logs"
    main(
        ["train", "--algo", "dream", "--env", "MetaBus-v0", "-n", "120", "--seed", "0", "--num-threads", "1",
         "-f", str(logs), "-params", *TINY["dream"], "learning_starts:50"]
    )  # fmt: skip
    assert "('learning_starts', 50)" in capsys.readouterr().out
    model = DREAM.load(logs / "dream" / "MetaBus-v0_1" / "MetaBus-v0.zip")
    assert model.learning_starts == 50 and model.num_timesteps == 120
    # SB3's names that DREAM has no use for are errors naming its own, not silently ignored.
    with pytest.raises(ValueError, match="DREAM does not take SB3's 'exploration_fraction': .*eps_decay_steps"):
        main(["train", "--algo", "dream", "--env", "MetaBus-v0", "-n", "8", "-f", str(logs), "-params",
              *TINY["dream"], "exploration_fraction:0.1"])  # fmt: skip
