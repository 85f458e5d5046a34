"""The exploration figures (the paper's Figures 7-9): paths read from known explorations, the 2-D
embedding's fallback, and examples/exploration_figures.py on the shipped models."""

from __future__ import annotations

import csv
import importlib.util
import pathlib
import sys
import types

import gymnasium as gym
import numpy as np
import pytest

import dream_envs  # noqa: F401  (registers the envs)
from dream_envs import ScriptedAgent
from dream_envs.bus import END_EPISODE, GRAY_STOPS, RIDE, RIGHT, UP
from dream_envs.figures import (
    PATH_COLUMNS,
    ExplorationEvent,
    exploration_paths,
    held_out_problems,
    path_rows,
    summary,
)
from sb3_dream import code_figures
from sb3_dream.code_figures import embed_2d, pca_2d

ROOT = pathlib.Path(__file__).resolve().parents[1]
DREAM_MAP = ROOT / "models" / "dream_metabus_map.zip"
RL2DQN_MAP = ROOT / "models" / "rl2dqn_metabus_map.zip"


class Script(ScriptedAgent):
    """Plays ``actions`` while exploring (then the end-episode action), and ends every execution episode."""

    def __init__(self, actions):
        self.actions = list(actions)

    def reset(self) -> None:
        self.t = 0

    def act(self, obs, info) -> int:
        if int(obs["phase"]) != 0 or self.t >= len(self.actions):
            return END_EPISODE
        self.t += 1
        return self.actions[self.t - 1]


@pytest.fixture(scope="module")
def script_module():
    spec = importlib.util.spec_from_file_location("exploration_figures", ROOT / "examples" / "exploration_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_scripted_ride_gives_the_hand_known_path():
    # distracting bus, problem 23: colored permutation 23 = (3, 2, 1, 0), so stop A (4, 5) leads to
    # (8, 7); gray permutation 0, so g1 (5, 5) leads to (0, 4)
    env = gym.make("MetaBus-v0", variant="distracting", split="all")
    routes = env.unwrapped.routes(23)
    assert routes[(4, 5)] == (8, 7) and routes[GRAY_STOPS[0]] == (0, 4)
    (path,) = exploration_paths(env, Script([UP, RIDE, RIDE, RIGHT, RIDE]), 1, problem_ids=[23])
    assert path.problem_id == 23
    assert path.cells == [(4, 4), (4, 5), (8, 7), (4, 5), (5, 5), (0, 4), (0, 4)]
    assert path.actions == [UP, RIDE, RIDE, RIGHT, RIDE, END_EPISODE]
    assert path.events == [
        ExplorationEvent(1, "ride", "A", (4, 5)),
        ExplorationEvent(2, "ride", "A", (8, 7)),  # riding back sees the same route
        ExplorationEvent(4, "ride", "g1", (5, 5)),
    ]
    assert path.labels("ride") == ["A", "g1"] and path.length == 6
    assert summary(env, [path]) == "colored routes 1.0, gray routes 1.0, 6.0 steps"

    # the map variant's oracle walks to the map and reads it on its fourth step
    env = gym.make("MetaBus-v0", variant="map", split="test")
    (path,) = exploration_paths(env, env.unwrapped.oracle(), 1, problem_ids=[7])
    assert path.cells == [(4, 4), (5, 4), (6, 4), (7, 4), (7, 3), (7, 3)]
    assert path.events == [ExplorationEvent(3, "map", "map", (7, 3))]
    assert summary(env, [path]) == "colored routes 0.0, map read in 1/1, 5.0 steps"

    # MetaCook's oracle opens the middle fridge, then the bottom one, then the top one
    env = gym.make("MetaCook-v0", split="all")
    (path,) = exploration_paths(env, env.unwrapped.oracle(), 1, problem_ids=[0 + 1 * 7 + 2 * 49])  # fridges (1, 2, 3)
    assert path.cells == [(1, 1), (2, 1), (2, 1), (2, 0), (2, 0), (2, 1), (2, 2), (2, 2), (2, 2)]
    assert [(e.step, e.label) for e in path.events] == [(1, "F1: 2"), (3, "F0: 1"), (6, "F2: 3")]
    assert summary(env, [path]).startswith("fridges opened 3.0 (all 3 in 1/1)")


def test_path_rows_hold_every_state_with_its_offset_and_finding():
    env = gym.make("MetaBus-v0", variant="distracting", split="all")
    paths = exploration_paths(env, Script([UP, RIDE]), 2, problem_ids=[23, 22])
    rows = path_rows(env, {"script": paths})
    assert len(rows) == 2 * 4 and all(len(r) == len(PATH_COLUMNS) for r in rows)
    first = [r for r in rows if r[1] == 0]
    assert [(r[4], r[5]) for r in first] == [(4, 4), (4, 5), (8, 7), (8, 7)]
    assert [r[9] for r in first] == ["up", "ride", "end", ""] and first[1][10] == "ride A"
    # the two trials are drawn shifted apart along the diagonal, by opposite offsets
    shift = {r[1]: r[6] - r[4] for r in rows}
    assert shift[0] == pytest.approx(-shift[1]) and shift[0] < 0
    assert all(r[6] - r[4] == pytest.approx(r[7] - r[5]) for r in rows)


def test_held_out_problems_are_distinct_before_repeating():
    env = gym.make("MetaBus-v0", variant="map", split="test")
    ids = held_out_problems(env, 30, seed=1)
    assert len(set(ids[:24].tolist())) == 24 and ids[24:].tolist() == ids[:6].tolist()
    with pytest.raises(ValueError, match="n=0 must be a number of problems"):
        held_out_problems(env, 0)


def test_the_embedding_falls_back_to_pca_without_scikit_learn(monkeypatch):
    rng = np.random.default_rng(0)
    # points on a line in 5-D: PCA keeps their distances on its first axis and nothing on the second
    line = np.outer(np.arange(6.0), rng.normal(size=5))
    xy = pca_2d(line)
    assert np.allclose(xy[:, 1], 0, atol=1e-9)
    assert np.allclose(np.abs(np.diff(xy[:, 0])), np.linalg.norm(line[1] - line[0]))

    monkeypatch.setitem(sys.modules, "sklearn", None)  # an import of it now fails
    monkeypatch.setitem(sys.modules, "sklearn.manifold", None)
    points = rng.normal(size=(12, 4))
    xy, used = embed_2d(points, "auto")
    assert used == "pca" and xy.shape == (12, 2) and np.allclose(xy, pca_2d(points))
    with pytest.raises(ImportError, match="needs scikit-learn"):
        embed_2d(points, "tsne")
    with pytest.raises(ValueError, match="embedding='umap' is not valid"):
        embed_2d(points, "umap")

    # with scikit-learn importable, "auto" takes its t-SNE (a stand-in here records the call)
    calls = {}

    class TSNE:
        def __init__(self, **kwargs):
            calls.update(kwargs)

        def fit_transform(self, x):
            return x[:, :2] * 0 + 1

    manifold = types.ModuleType("sklearn.manifold")
    manifold.TSNE = TSNE
    monkeypatch.setitem(sys.modules, "sklearn", types.ModuleType("sklearn"))
    monkeypatch.setitem(sys.modules, "sklearn.manifold", manifold)
    xy, used = embed_2d(points, "auto", seed=3)
    assert used == "tsne" and calls["n_components"] == 2 and calls["random_state"] == 3
    assert calls["perplexity"] < len(points)  # t-SNE refuses a perplexity of n or more


def test_dream_codes_of_the_shipped_map_model_land_on_their_problems():
    from sb3_dream import DREAM

    model = DREAM.load(DREAM_MAP, device="cpu")
    codes = code_figures.dream_codes(model, "MetaBus-v0", n_trials=6, env_kwargs={"variant": "map"}, n_envs=3)
    assert codes.f.shape[0] == 24 and codes.g.shape == (6, codes.f.shape[1]) and codes.family == "MetaBusEnv"
    assert len(set(codes.trial_problem_ids.tolist())) == 6
    for k, prefix in enumerate(codes.prefixes):
        np.testing.assert_allclose(prefix[-1], codes.g[k], atol=1e-5)  # the whole trajectory's prefix is g
    # the model reads the map in every exploration: g(tau^exp) is its problem's f(T)
    error = ((codes.g - codes.f[codes.trial_problem_ids]) ** 2).sum(axis=1)
    spread = ((codes.f[:, None] - codes.f[None]) ** 2).sum(axis=2).mean()
    assert error.max() < 0.05 * spread
    distances = code_figures.code_distances(codes)
    assert distances["decoder_error"] == pytest.approx(error.mean()) and distances["decoder_error"] < 0.05
    # before it has seen anything the decoder guesses the mean of the problems' codes
    assert distances["empty_to_mean_f"] < 0.05 * distances["f_spread"]
    values, name = code_figures.color_values(codes, 0)
    assert values.tolist() == list(range(24)) and name.startswith("colored permutation")
    with pytest.raises(ValueError, match="color_by=5 is not valid"):
        code_figures.color_values(codes, 5)
    with pytest.raises(TypeError, match="model must be a DREAM model"):
        code_figures.dream_codes(object(), "MetaBus-v0", 1)


def test_decode_prefixes_ends_with_dreams_decode_of_the_whole_trajectory():
    from sb3_dream import DREAM
    from sb3_dream.dream.acting import decode

    model = DREAM.load(DREAM_MAP, device="cpu")
    env = gym.make("MetaBus-v0", variant="map")
    rng = np.random.default_rng(0)
    trajectories = []
    for length in (5, 0, 12):  # unequal lengths, one with nothing explored
        obs, _ = env.reset(seed=length)
        states, actions = [obs["obs"]], rng.integers(0, env.action_space.n, size=length)
        for action in actions:
            obs, *_ = env.step(int(action))
            states.append(obs["obs"])
        trajectories.append((np.stack(states), actions))
    prefixes = model.decode_prefixes(trajectories)
    assert [p.shape for p in prefixes] == [(n + 1, model.policy.z_dim) for n in (5, 0, 12)]
    # DREAM's own decode at meta-test, g(tau^exp), from the same trajectories in its trial state
    state = model.new_trial_state(len(trajectories))
    for k, (states, actions) in enumerate(trajectories):
        state.states[k, : len(states)], state.actions[k, : len(actions)] = states, actions
    lengths = np.array([len(a) for _, a in trajectories])
    whole = decode(model.policy, state, np.arange(len(trajectories)), lengths)
    np.testing.assert_allclose(np.stack([p[-1] for p in prefixes]), whole, atol=1e-6)
    # and every prefix is the decode of that many transitions
    for t in range(13):
        alone = decode(model.policy, state, np.array([2]), np.array([t]))[0]
        np.testing.assert_allclose(prefixes[2][t], alone, atol=1e-6)
    with pytest.raises(ValueError, match="trajectory 0: states must be"):
        model.decode_prefixes([(trajectories[0][0], trajectories[0][1][:-1])])
    with pytest.raises(ValueError, match="trajectories is empty"):
        model.decode_prefixes([])


def read_csv(path: pathlib.Path):
    with open(path, newline="") as handle:
        return list(csv.reader(handle))


def test_the_script_draws_the_shipped_models(tmp_path, script_module, capsys):
    out = tmp_path / "figs" / "map"
    script_module.main([
        "--env-kwargs", "variant=map", "--trials", "2", "--oracle",
        "--model", f"DREAM={DREAM_MAP}", "--model", f"RL2DQN={RL2DQN_MAP}", "--out", str(out),
    ])  # fmt: skip
    png, table = tmp_path / "figs" / "map_explorations.png", tmp_path / "figs" / "map_explorations.csv"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = read_csv(table)
    assert tuple(rows[0]) == PATH_COLUMNS
    panels = {r[0] for r in rows[1:]}
    assert panels == {"optimal (scripted)", "DREAM", "RL2DQN"}
    # every panel plays the same problems; DREAM reads the map in both, RL2DQN in neither
    problems = {p: {r[2] for r in rows[1:] if r[0] == p} for p in panels}
    assert len({frozenset(v) for v in problems.values()}) == 1
    maps = {p: sum(r[10] == "map map" for r in rows[1:] if r[0] == p) for p in panels}
    assert maps == {"optimal (scripted)": 2, "DREAM": 2, "RL2DQN": 0}

    script_module.main([
        "--env-kwargs", "variant=map", "--trials", "6", "--codes", "--embedding", "pca",
        "--model", str(RL2DQN_MAP), "--model", str(DREAM_MAP), "--out", str(out),
    ])  # fmt: skip
    assert "(dream_metabus_map, pca)" in capsys.readouterr().out
    assert (tmp_path / "figs" / "map_codes.png").stat().st_size > 10_000
    rows = read_csv(tmp_path / "figs" / "map_codes.csv")
    kinds = [r[0] for r in rows[1:]]
    assert kinds.count("f") == 24 and kinds.count("g") == 6 and kinds.count("g_prefix") > 3


def test_a_model_trained_with_rewarded_exploration_plays_in_that_env(tmp_path, script_module, capsys):
    # E-RL2 (the paper's dashed line) sees an instruction and rewards while exploring: its panel is
    # played with reward_free_exploration=False, beside a reward-free model on the same problems
    from sb3_dream import RL2DQN

    e_rl2 = RL2DQN(gym.make("MetaBus-v0", variant="map", reward_free_exploration=False), seed=0)
    e_rl2.save(tmp_path / "e_rl2")
    assert e_rl2.trial_spec["reward_free_exploration"] is False
    out = tmp_path / "mixed"
    script_module.main([
        "--env-kwargs", "variant=map", "--trials", "2",
        "--model", f"DREAM={DREAM_MAP}", "--model", f"E-RL2={tmp_path / 'e_rl2.zip'}", "--out", str(out),
    ])  # fmt: skip
    rows = read_csv(tmp_path / "mixed_explorations.csv")
    problems = {p: {r[2] for r in rows[1:] if r[0] == p} for p in ("DREAM", "E-RL2")}
    assert problems["DREAM"] == problems["E-RL2"] and len(problems["DREAM"]) == 2

    parser = script_module.build_parser()
    args = parser.parse_args(["--env-kwargs", "variant=map", "--model", "x", "--out", "o"])
    env = gym.make("MetaBus-v0", variant="map", split="test")
    played = script_module.model_env(parser, args, {"variant": "map"}, e_rl2, env)
    assert played is not env and played.unwrapped.reward_free_exploration is False
    assert played.unwrapped.split == "test" and played.unwrapped.variant == "map"
    # asking for the reward-free env explicitly keeps it, and the model is refused there
    capsys.readouterr()
    with pytest.raises(SystemExit):
        script_module.main([
            "--env-kwargs", "variant=map", "reward_free_exploration=True",
            "--model", str(tmp_path / "e_rl2.zip"), "--out", str(out),
        ])  # fmt: skip
    assert "its reward_free_exploration is True, the model's is False" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--trials", "0"], "--trials must be a number of trials >= 1, got 0"),
        (["--env", "SignNav3D-v0"], "--env must be one of MetaBus-v0, MetaCook-v0"),
        (["--model", "gone.zip"], "--model: no such file: gone.zip"),
        (["--color-by", "red"], "--color-by must be a problem feature index"),
        (["--prefix-paths", "-1"], "--prefix-paths must be a number of trials >= 0"),
        (["--env-kwargs", "variant"], "--env-kwargs entries must look like key=value"),
        (["--env-kwargs", "variant=tram"], "--env-kwargs variant=tram for MetaBus-v0: variant='tram'"),
        (["--model", f"A={DREAM_MAP}", "--model", f"A={RL2DQN_MAP}"], "--model: the label 'A' is given twice"),
        (["--env-kwargs", "variant=distracting"], f"--model {DREAM_MAP}: the env (--env, --env-kwargs) does not match"),
        (["--codes", "--model", str(RL2DQN_MAP)], "--codes needs a DREAM --model"),
        (["--codes", "--color-by", "3"], "--color-by: color_by=3 is not valid"),
        ([], "--model is required"),
    ],
)
def test_bad_arguments_are_refused_naming_the_argument(tmp_path, script_module, capsys, args, message):
    defaults = ["--env-kwargs", "variant=map"] if "--env-kwargs" not in args else []
    model = [] if "--model" in args or args == [] else ["--model", str(DREAM_MAP)]
    argv = defaults + model + args + ["--out", str(tmp_path / "x")]
    with pytest.raises(SystemExit) as exit_info:
        script_module.main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("env_id,kwargs", [("MetaCook-v0", {}), ("MetaBus-v0", {"variant": "map"})])
def test_figure_legend_names_what_each_trial_found_within_its_panel(env_id, kwargs):
    plt = pytest.importorskip("matplotlib.pyplot")
    from dream_envs.figures import exploration_figure

    env = gym.make(env_id, split="test", **kwargs)
    paths = exploration_paths(env, env.unwrapped.oracle(), 6)
    fig = exploration_figure(env, {"a": paths, "b": paths})
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        legend = ax.get_legend()
        labels = [t.get_text() for t in legend.get_texts()]
        if env_id == "MetaCook-v0":
            # the fridges in the order opened; the contents are in the problem's part of the label
            assert all(" opened F1, F0, F2 (8 steps)" in label for label in labels[:6]), labels
        # the legend stays under its own panel: side by side, two panels' legends do not overlap
        assert legend.get_window_extent(renderer).width <= ax.get_window_extent(renderer).width
    plt.close(fig)
