"""The example scripts (and the research probe) run end to end on tiny budgets, and the custom env example is a correct
trial env."""

from __future__ import annotations

import csv
import importlib.util
import pathlib
import shutil
import subprocess
import sys
import zipfile

import cv2
import numpy as np
import pytest

from dream_envs import play_trial
from sb3_dream.evaluation import evaluate_meta

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
RESEARCH = ROOT / "research"  # research probes: scripts beside the package, not usage examples
TINY_DREAM = [
    "exploration_learning_starts=5", "execution_learning_starts=5", "buffer_size=200", "execution_buffer_size=1000"
]  # fmt: skip


def load_example(name: str, folder: pathlib.Path = EXAMPLES):
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_example(name: str, *args: str, cwd: pathlib.Path, folder: pathlib.Path = EXAMPLES) -> str:
    result = subprocess.run(
        [sys.executable, str(folder / name), *args], cwd=cwd, capture_output=True, text=True, timeout=180
    )
    assert result.returncode == 0, f"{name} failed:\n{result.stdout}\n{result.stderr}"
    return result.stdout


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """examples/train_dream_metabus.py on a tiny budget: the saved model and the script's output."""
    folder = tmp_path_factory.mktemp("train")
    out = run_example(
        "train_dream_metabus.py", "--variant", "map", "--steps", "200", "--eval-freq", "100", "--eval-trials", "3",
        "--out", "model.zip", "--dream-kwargs", *TINY_DREAM, cwd=folder,
    )  # fmt: skip
    return folder / "model.zip", out


def test_train_dream_metabus(trained):
    model, out = trained
    assert model.exists()
    assert out.count("test: execution return") == 3  # evaluations at 0, 100 and 200 steps
    assert "held-out: execution return" in out


def test_watch_dream_writes_mp4_and_gif(trained, tmp_path):
    model, _ = trained
    out = run_example(
        "watch_dream.py", "--model", str(model), "--env-kwargs", "variant='map'", "--n-exec-episodes", "2",
        "--out", "trial.mp4", "--fps", "4", cwd=tmp_path,
    )  # fmt: skip
    n_frames = int(out.split("(")[1].split(" frames")[0])
    video = cv2.VideoCapture(str(tmp_path / "trial.mp4"))
    frames = []
    while True:
        ok, frame = video.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == n_frames > 3 * 4  # title cards for the exploration and both execution episodes
    assert "execution returns" in out and out.count(", ") >= 1

    out = run_example("watch_dream.py", "--oracle", "--out", "oracle.gif", "--problem-id", "5", cwd=tmp_path)
    assert "execution returns +0.80" in out  # the oracle on the distracting bus
    if hasattr(cv2, "imreadanimation"):
        ok, animation = cv2.imreadanimation(str(tmp_path / "oracle.gif"))
        assert ok and len(animation.frames) > 10 and animation.frames[0].shape[2] == 3
    else:
        assert (tmp_path / "oracle.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")


def test_meta_test_gains_on_metacook_name_each_fridge_opening(tmp_path):
    from sb3_dream import DREAM

    # An untrained model: what its greedy explorer does matters not here, only the MetaCook report's form.
    DREAM("MetaCook-v0", seed=0, buffer_size=200, execution_buffer_size=1000).save(tmp_path / "cook.zip")
    out = run_example(
        "meta_test.py", "--model", str(tmp_path / "cook.zip"), "--env", "MetaCook-v0", "--trials", "3", "--gains",
        cwd=tmp_path,
    )  # fmt: skip
    assert "DREAM exploration reward per step (Equation 5, c = 0.01; " in out
    line = next(row for row in out.splitlines() if "exploration reward of a fridge's first opening: " in row)
    assert line.endswith("no fridge opened") or " opened first in " in line
    # the oracle's explorations, rewarded by the model: fridges 1, 0 and 2 in every trial, nearest first
    out = run_example(
        "meta_test.py", "--model", str(tmp_path / "cook.zip"), "--env", "MetaCook-v0", "--trials", "3", "--gains",
        "--gains-explorer", "oracle", cwd=tmp_path,
    )  # fmt: skip
    assert "DREAM (oracle explorations) exploration reward per step" in out
    assert "fridge 1 opened first in 3 trials: " in out and "fridge 0 opened second in 3 trials: " in out
    assert "fridge 2 opened third in 3 trials: " in out


def test_meta_test_compares_with_the_oracle(trained, tmp_path):
    model, _ = trained
    out = run_example(
        "meta_test.py",
        "--model",
        str(model),
        "--env-kwargs",
        "variant='map'",
        "--trials",
        "4",
        "--outcomes",
        cwd=tmp_path,
    )
    assert "split=test (24 problems), 4 trials" in out
    assert "DREAM: execution return" in out and "optimal (scripted): execution return 0.800" in out
    # --outcomes: the oracle's every episode pays 0.8, under its summary line
    oracle_outcomes = out.split("optimal (scripted): ")[1].splitlines()[1].strip()
    assert oracle_outcomes == "return > 0 in 100%, < 0 in 0%, 0 in 0% of execution episodes"
    diagnose_args = ["--model", str(model), "--env-kwargs", "variant=map", "--trials", "3", "--diagnose"]
    out = run_example("meta_test.py", *diagnose_args, "--exploration", "--trace", "2", "--gains", cwd=tmp_path)
    # --gains: Equation 5's reward of each exploration step, per step, and the trial's information gain
    assert "DREAM exploration reward per step (Equation 5, c = 0.01; mean over the trials that took it): " in out
    assert "; information gain per trial " in out and "first opening" not in out  # fridges: MetaCook only
    # ... and on MetaBus, by what each step found (the map variant: the map, and any other step)
    assert "DREAM exploration reward by what the step found: " in out and " steps)" in out
    # --trace: each agent's first two explorations, by action name; the oracle reads the map.
    assert out.count("optimal (scripted) trial ") == 2 and out.count("DREAM trial ") == 2
    assert "optimal (scripted) trial 0, problem " in out and ": right right right down end\n" in out
    assert "diagnosis: return with z = g " in out and "with z = f(T) " in out and "with z ~ N(f(T), rho^2 I) " in out
    assert "with z = g of the optimal exploration " in out and "(optimal exploration: " in out
    # The oracle reads the map in every trial and ends the exploration episode after 5 steps.
    assert "optimal (scripted) exploring: colored routes seen 0.00" in out
    assert "map read 100%, exploration length 5.0, execution return 0.800" in out
    assert "DREAM exploring: colored routes seen" in out and "random exploring:" in out
    assert "DREAM with z = f(T): colored routes seen" in out  # the report for the privileged agent
    # several models: one line each, named by their files, and one diagnosis each
    copy = tmp_path / "copy.zip"
    shutil.copy(model, copy)
    out = run_example("meta_test.py", "--model", str(model), str(copy), *diagnose_args[2:], cwd=tmp_path)
    for path in (model, copy):
        assert f"{path}: execution return" in out and f"{path} diagnosis: return with z = g" in out
    assert out.count("optimal (scripted): execution return") == 1

    refused = subprocess.run(
        [sys.executable, str(EXAMPLES / "meta_test.py"), "--model", str(model), "--trace", "-1"],
        cwd=tmp_path, capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert refused.returncode == 2 and "--trace must be a number of trials >= 0, got -1" in refused.stderr
    missing = subprocess.run(
        [sys.executable, str(EXAMPLES / "meta_test.py"), "--model", str(model), "gone.zip"],
        cwd=tmp_path, capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert missing.returncode == 2 and "--model: no such file: gone.zip" in missing.stderr

    meta_test = load_example("meta_test")
    assert type(meta_test.load_model(str(model))).__name__ == "DREAM"
    with zipfile.ZipFile(tmp_path / "dqn.zip", "w") as archive:
        archive.writestr("data", '{"policy_class": {"__module__": "stable_baselines3.dqn.policies"}}')
    with pytest.raises(ValueError, match="holds none of DREAM, RL2DQN, IMPORT, VariBAD"):
        meta_test.load_model(str(tmp_path / "dqn.zip"))


def test_meta_test_diagnoses_an_import_model(tmp_path):
    import gymnasium as gym

    from sb3_dream import IMPORT

    path = tmp_path / "import.zip"
    IMPORT("MultiInputLstmPolicy", gym.make("MetaBus-v0", variant="map"), seed=0).save(path)
    args = ["--model", str(path), "--env-kwargs", "variant=map", "--trials", "3", "--diagnose"]
    out = run_example("meta_test.py", *args, cwd=tmp_path)
    assert "IMPORT: execution return" in out
    assert "diagnosis: return with z = e(tau) " in out and ", with z = e(T) " in out
    assert " exploring, " in out and " executing, against ||e(T) - e(T')||^2 " in out
    out = run_example("meta_test.py", *args, "--exhaustive", cwd=tmp_path)
    assert "split=test (24 problems), 96 trials" in out  # every held-out (problem, instruction) pair
    assert "diagnosis: return with z = e(tau) " in out


@pytest.mark.opengl
def test_meta_test_plays_the_sign_oracle_on_the_env_it_reads(tmp_path):
    # SignNav3D's oracle navigates by its env's pose: it must play on that env, not on a fresh copy
    from sb3_dream import DREAM

    DREAM("SignNav3D-v0", seed=0, buffer_size=20, execution_buffer_size=20).save(tmp_path / "sign.zip")
    out = run_example(
        "meta_test.py", "--model", str(tmp_path / "sign.zip"), "--env", "SignNav3D-v0", "--trials", "2", cwd=tmp_path
    )
    assert "optimal (scripted): execution return 1.000 ± 0.000 over 2 trials" in out


def test_replay_rewards_counts_a_saved_buffer_per_problem_and_instruction(tmp_path):
    from sb3_dream import DREAM

    model = DREAM("MetaBus-v0", seed=0, exploration_learning_starts=5, execution_learning_starts=5)
    model.learn(300)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    counts = model.replay_buffer.execution_reward_counts()
    out = run_example("replay_rewards.py", "buffer.pkl", cwd=tmp_path)
    lines = out.splitlines()
    assert lines[0] == f"buffer.pkl: {len(model.replay_buffer.execution)} execution transitions"
    assert len(lines) == 1 + len(counts.transitions) + (counts.unlinked > 0)
    p, i, n = counts.problem_features[0], counts.instructions[0], counts.transitions[0]
    assert f"problem {tuple(p.tolist())} instruction {tuple(i.tolist())}: {n} transitions" in lines[1]
    assert sum(counts.transitions) + counts.unlinked == len(model.replay_buffer.execution)

    from stable_baselines3.common.save_util import save_to_pkl

    save_to_pkl(tmp_path / "other.pkl", {"not": "a buffer"})
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "replay_rewards.py"), "other.pkl"], cwd=tmp_path, capture_output=True, text=True
    )
    assert result.returncode != 0 and "other.pkl holds a dict, not a DREAM replay buffer" in result.stderr


def test_custom_trial_env_script(tmp_path):
    out = run_example("custom_trial_env.py", "--steps", "120", "--n-envs", "2", "--eval-trials", "10", cwd=tmp_path)
    assert "oracle: execution return 1.000" in out and "DREAM: execution return" in out


def test_custom_trial_env_is_a_working_imrl_problem():
    module = load_example("custom_trial_env")
    env = module.SignCorridorEnv(split="test", n_exec_episodes=2)
    assert evaluate_meta(env.oracle(), env, n_trials=8, n_exec_episodes=2).mean == 1.0

    class NoExploration(module.SignCorridorOracle):
        """Stops exploring at once, then must walk to the sign in the first execution episode."""

        def act(self, obs, info):
            if int(obs["phase"]) == 0:
                return module.STOP
            return super().act(obs, info)

    result = play_trial(env, NoExploration(), seed=0)
    assert result["exploration_length"] == 1
    np.testing.assert_allclose(result["execution_returns"], [0.7, 1.0])  # walks 3 cells once, then knows
    obs, info = env.reset(options={"problem_id": 2})
    assert "problem_id" not in obs and info["problem_id"] == 2 and obs["obs"].tolist() == [0, 0]
    with pytest.raises(ValueError, match="length and n_codes"):
        module.SignCorridorEnv(length=1)


def test_cook_composition_probe_targets_are_optimal_and_the_script_writes_its_table(tmp_path):
    probe = load_example("cook_composition_probe", RESEARCH)
    from dream_envs import cook

    rng = np.random.default_rng(0)
    for k in rng.choice(cook.N_PROBLEMS, 30, replace=False):
        for recipe in cook.valid_instructions(int(k)):
            states, q = probe.optimal_q(int(k), recipe)  # greedy on Q* cooks the recipe optimally
            index, state, total = {s: j for j, s in enumerate(states)}, (*cook.START, 0, 0, 0), 0.0
            for _ in range(probe.HORIZON):
                action = probe.ACTIONS[int(q[index[state]].argmax())]
                state, reward, done = cook.cook_transition(state, action, cook.fridge_contents(int(k)), recipe)
                total += reward
                if done:
                    break
            assert done and total == pytest.approx(cook.optimal_execution_return(int(k), recipe))
            # Q* is the fixed point of the bootstrapped targets: r + gamma max_a' Q*(s', a') = Q*
            _, *transitions = probe.kitchen_mdp(int(k), recipe)
            np.testing.assert_allclose(probe.bellman_targets(q.max(axis=1), *transitions), q, atol=1e-6)
    for flags in ([], ["--targets", "bootstrapped", "--actions", "one", "--target-update", "2"]):
        run_example(
            "cook_composition_probe.py", "--variants", "wide_parts", "--seeds", "0", "--steps", "3",
            "--out", "probe.csv", *flags, cwd=tmp_path, folder=RESEARCH,
        )  # fmt: skip
    with open(tmp_path / "probe.csv") as f:
        rows = list(csv.DictReader(f))  # the second command's rows appended to the first's
    assert [row["part"] for row in rows] == 2 * [
        "train", "test_problems", "test_instructions", "recipe 36", "recipe 71", "recipe 54"
    ]  # fmt: skip
    assert [int(row["pairs"]) for row in rows] == 2 * [2268, 25, 106, 36, 36, 34]
    assert [row["targets"] for row in rows] == 6 * ["optimal"] + 6 * ["bootstrapped"]
    assert all(0 <= float(row["cooked"]) <= 1 for row in rows)
    for flag, value in (("--target-update", "0"), ("--steps", "-1"), ("--lr", "0")):  # refused before any work
        result = subprocess.run(
            [sys.executable, str(RESEARCH / "cook_composition_probe.py"), flag, value],
            cwd=tmp_path, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert result.returncode == 2 and f"{flag} must be positive, got {value}" in result.stderr


def test_cook_composition_probe_fusions_change_one_place_of_the_wide_parts_network():
    probe = load_example("cook_composition_probe", RESEARCH)
    import gymnasium as gym
    import torch as th

    space = gym.make("MetaCook-v0").observation_space
    states, recipes, z = th.zeros(4, 6, dtype=th.long), th.tensor([[3, 6], [6, 3], [7, 1], [1, 7]]), th.randn(4, 64)
    base = dict(probe.q_network("wide_parts", space).named_children())
    added_or_replaced = {"film_parts": {"film_state", "film_recipe"}, "shared_parts": {"instruction_embed"}}
    for variant in probe.FUSIONS:
        q_net = probe.q_network(variant, space)
        assert q_net(states, recipes, z)[0].shape == (4, 9)
        changed = {name for name, child in q_net.named_children() if type(child) is not type(base.get(name))}
        assert changed == added_or_replaced.get(variant, set())
    # shared_parts: an ingredient has one embedding, first or second in the recipe
    parts = probe.q_network("shared_parts", space).instruction_embed(recipes).reshape(4, 2, -1)
    assert th.equal(parts[0, 0], parts[1, 1]) and th.equal(parts[2, 1], parts[3, 0])
    assert not th.equal(parts[0, 0], parts[0, 1])
    # film_parts: the recipe multiplies into the first layer; state_parts: no MLP over the state
    film = probe.q_network("film_parts", space)
    assert film.film_recipe.in_features == film.instruction_embed.embed_dim == 64
    assert probe.q_network("state_parts", space).state_embed.embed_dim == 6 * 32
    with pytest.raises(ValueError, match="variant='deep' is not one of"):
        probe.q_network("deep", space)


def test_cook_q_head_probe_is_rl2s_network_with_one_more_layer_and_trains_through_the_runner(tmp_path):
    probe = load_example("cook_q_head_probe", RESEARCH)
    from torch import nn

    from sb3_dream import RL2DQN
    from sb3_dream.experiments.algorithms import ALGORITHMS

    assert ALGORITHMS[probe.NAME].load_class() is probe.ReluHeadRL2DQN
    rl2 = RL2DQN("MetaBus-v0", seed=0).policy.q_net
    model = probe.ReluHeadRL2DQN("MetaBus-v0", seed=0, policy_kwargs={"head_hidden_dim": 32})
    q_net = model.policy.q_net
    shapes = {name: p.shape for name, p in rl2.named_parameters() if not name.startswith("head.")}
    assert {name: p.shape for name, p in q_net.named_parameters() if not name.startswith("head.")} == shapes
    assert q_net.head[0].in_features == rl2.lstm_hidden_size and q_net.head[0].out_features == 32
    assert isinstance(q_net.head[1], nn.ReLU) and type(q_net.head[2]) is type(rl2.head)
    run_example(
        "cook_q_head_probe.py", "--envs", "MetaBus-v0:variant=map", "--algos", probe.NAME, "--seeds", "0",
        "--steps", "400", "--n-envs", "2", "--preset", "fast", "--eval-freq", "200", "--eval-trials", "2",
        "--jobs", "1", "--threads", "1", "--save-models", "--out", "probe", cwd=tmp_path, folder=RESEARCH,
    )  # fmt: skip
    folder = tmp_path / "probe" / "MetaBus-v0_variant-map"
    curve = (folder / f"{probe.NAME}_seed0.csv").read_text().splitlines()
    assert [row["env_steps"] for row in csv.DictReader(curve)] == ["0", "200", "400"]
    loaded = probe.ReluHeadRL2DQN.load(folder / f"{probe.NAME}_seed0.zip")
    # the script ran as __main__, so the zip holds its classes by value: the same names and layers
    assert type(loaded.policy.q_net).__name__ == "ReluHeadQNetwork" and loaded.policy.q_net.head[0].out_features == 64
