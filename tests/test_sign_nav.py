"""SignNav3D-v0: spaces, rewards, the sign, seeding, checkers, the OpenGL error and the oracle."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import dream_envs
from dream_envs import ScriptedAgent, play_trial, public_info, sign_nav
from dream_envs.sign_nav import engine
from dream_envs.sign_nav import (
    END_EPISODE,
    MOVE_FORWARD,
    SIGN_CENTER,
    TURN_LEFT,
    OpenGLUnavailableError,
    SignNav3DEnv,
    sign_colour_from_image,
)

BALL, KEY, BOX = [1], [2], [3]
BLUE, RED = 0, 1


@pytest.fixture(scope="module")
def env():
    env = SignNav3DEnv()
    yield env
    env.close()


def start_execution(env, problem_id, instruction, seed=0):
    """Reset with a pinned problem and instruction, and end the exploration episode at once."""
    env.reset(seed=seed, options={"problem_id": problem_id, "instruction": instruction})
    obs, reward, terminated, _, info = env.step(END_EPISODE)
    assert info["episode_end"] and info["episode_phase"] == 0 and reward == 0.0 and not terminated
    return obs


def place_before(env, kind, colour):
    """Put the agent one forward step away from touching object (kind, colour), facing it."""
    [pos] = [p for k, c, p in env.object_positions() if (k, c) == (kind, colour)]
    i = [(k, c) for k, c, _ in env.object_positions()].index((kind, colour))
    reach = env._touch_distance[i] + 0.4  # > touch distance, < touch distance + one 0.7 m step
    for angle in np.linspace(0, 2 * math.pi, 16, endpoint=False):
        start = pos + reach * np.array([math.cos(angle), math.sin(angle)])
        inside = any(room.point_inside(np.array([start[0], 0.0, start[1]])) for room in env._world.rooms)
        if inside and env._touched(start) is None and not env._blocked(start):
            away = pos - start
            env._set_agent_pose(start[0], start[1], math.atan2(-away[1], away[0]))
            return
    raise AssertionError(f"no free spot next to the {colour} {kind}")


def view_from(env, x, z, direction):
    env._set_agent_pose(x, z, direction)
    return env._world.render_obs()


@pytest.mark.opengl
def test_spaces_and_splits(env):
    space = env.observation_space
    assert set(space.spaces) == {"obs", "instruction", "phase", "episode_start", "prev_action", "prev_reward"}
    assert space["obs"] == gym.spaces.Box(0, 255, (60, 80, 3), np.uint8)
    assert np.array_equal(space["instruction"].nvec, [4])
    assert env.action_space == gym.spaces.Discrete(4) and env.end_episode_action == 3
    assert env.n_problems == 2 and env.horizon == 20
    for split in ("train", "test", "all"):
        assert list(env.problem_ids(split)) == [0, 1]
    obs, info = env.reset(seed=0)
    assert space.contains(obs) and obs["obs"].std() > 10  # a real picture, not a blank frame
    assert np.array_equal(obs["instruction"], [0]) and obs["phase"] == 0
    assert "problem_id" in info and info["problem_id"] in (0, 1)


@pytest.mark.opengl
@pytest.mark.parametrize(
    "problem_id, instruction, kind, colour, expected",
    [
        (BLUE, BOX, "box", "blue", 1.0),  # right colour, right type
        (RED, BALL, "ball", "red", 1.0),
        (RED, BOX, "box", "blue", -1.0),  # wrong colour
        (BLUE, BALL, "key", "blue", -1.0),  # wrong type
    ],
)
def test_touching_rewards_and_ends_the_episode(env, problem_id, instruction, kind, colour, expected):
    start_execution(env, problem_id, instruction)
    place_before(env, kind, colour)
    obs, reward, terminated, _, info = env.step(MOVE_FORWARD)
    assert reward == expected
    assert terminated and info["episode_end"] and info["episode_length"] == 1
    assert info["execution_returns"] == [expected]


@pytest.mark.opengl
def test_turning_and_walking_in_the_open_give_nothing(env):
    start_execution(env, BLUE, BOX)
    env._set_agent_pose(5.0, 4.5, 0.0)
    for action in (0, 1, 1, MOVE_FORWARD):
        _, reward, terminated, _, info = env.step(action)
        assert reward == 0.0 and not terminated and "episode_end" not in info
    assert np.allclose(env.agent_position, [5.0 + 0.7 * math.cos(math.pi / 4), 4.5 + 0.7 * math.sin(math.pi / 4)])


@pytest.mark.opengl
def test_reward_free_exploration_touch_ends_episode_without_reward(env):
    obs, _ = env.reset(seed=1, options={"problem_id": BLUE})
    place_before(env, "box", "blue")  # the rewarding object for a box instruction: still 0 here
    obs, reward, terminated, _, info = env.step(MOVE_FORWARD)
    assert reward == 0.0 and not terminated
    assert info["episode_end"] and info["episode_phase"] == 0 and info["episode_length"] == 1
    assert obs["phase"] == 1 and obs["episode_start"] == 1 and obs["instruction"][0] in (1, 2, 3)
    assert obs["prev_reward"][0] == 0.0


@pytest.mark.opengl
def test_exploration_with_rewards_variant():
    env = SignNav3DEnv(reward_free_exploration=False)
    try:
        obs, _ = env.reset(seed=0, options={"problem_id": RED, "instruction": KEY})
        assert np.array_equal(obs["instruction"], KEY)
        place_before(env, "key", "red")
        _, reward, _, _, info = env.step(MOVE_FORWARD)
        assert reward == 1.0 and info["episode_phase"] == 0
    finally:
        env.close()


@pytest.mark.opengl
def test_the_sign_shows_the_problem_and_nothing_else_does(env):
    front = (SIGN_CENTER[0] - 2.5, SIGN_CENTER[2], 0.0)  # in front of the sign, facing it (east)
    elsewhere = [(5.0, 4.0, math.pi / 2), (7.5, 9.0, math.pi), (3.0, 10.0, -math.pi / 2)]  # top room; lower rooms
    views = {}
    for problem_id in (BLUE, RED):
        env.reset(seed=0, options={"problem_id": problem_id})
        views[problem_id] = [view_from(env, *pose) for pose in [front] + elsewhere]
    blue_sign, red_sign = views[BLUE][0], views[RED][0]
    differ = np.any(blue_sign != red_sign, axis=-1)
    assert 0.02 < differ.mean() < 0.5  # only the letters change
    assert sign_colour_from_image(blue_sign) == BLUE and sign_colour_from_image(red_sign) == RED
    rows, cols = np.nonzero(differ)
    assert rows.min() > 5 and rows.max() < 50 and cols.min() > 5 and cols.max() < 75  # within the board
    for a, b in zip(views[BLUE][1:], views[RED][1:]):
        assert np.array_equal(a, b)  # the sign out of view: the problem is invisible


@pytest.mark.opengl
def test_observation_carries_no_problem_id(env):
    """With the same seed, both problems give the same non-image observation and the same start view
    when the sign is not in view."""
    for seed in range(3):
        first = {}
        for problem_id in (BLUE, RED):
            obs, _ = env.reset(seed=seed, options={"problem_id": problem_id})
            first[problem_id] = obs
        for key in ("instruction", "phase", "episode_start", "prev_action", "prev_reward"):
            assert np.array_equal(first[BLUE][key], first[RED][key])
        if sign_colour_from_image(first[BLUE]["obs"]) is None:
            assert np.array_equal(first[BLUE]["obs"], first[RED]["obs"])


@pytest.mark.opengl
def test_seeding_is_reproducible(env):
    actions = [MOVE_FORWARD, 0, MOVE_FORWARD, 1, MOVE_FORWARD, END_EPISODE, MOVE_FORWARD, 0]

    def run(seed):
        obs, info = env.reset(seed=seed)
        images, rewards = [obs["obs"]], []
        for action in actions:
            obs, reward, terminated, _, info = env.step(action)
            images.append(obs["obs"])
            rewards.append(reward)
            if terminated:
                break
        return np.stack(images), rewards, info["problem_id"]

    a, b, c = run(7), run(7), run(8)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1] and a[2] == b[2]
    assert not np.array_equal(a[0][0], c[0][0])  # another seed, another start


@pytest.mark.opengl
def test_starts_are_random_behind_the_barrier(env):
    positions = []
    for seed in range(20):
        env.reset(seed=seed)
        positions.append(env.agent_position)
        assert env._touched(env.agent_position) is None
    positions = np.array(positions)
    assert np.all(positions[:, 1] < sign_nav.TOP_ROOM_DEPTH)  # the top room, across the barrier
    assert positions.std(axis=0).min() > 0.3


@pytest.mark.opengl
def test_pinned_problem_and_instruction(env):
    obs = start_execution(env, RED, KEY, seed=3)
    assert np.array_equal(obs["instruction"], KEY)
    _, info = env.reset(seed=3, options={"problem_id": RED})
    assert info["problem_id"] == RED


@pytest.mark.opengl
@pytest.mark.parametrize(
    "options",
    [{"problem_id": 2}, {"problem_id": -1}, {"instruction": [0]}, {"instruction": [4]}, {"instruction": [1, 2]}],
)
def test_bad_reset_options(env, options):
    with pytest.raises(ValueError, match="options"):
        env.reset(seed=0, options=options)


@pytest.mark.opengl
def test_bad_constructor_arguments_and_actions(env):
    with pytest.raises(ValueError, match="split"):
        SignNav3DEnv(split="val")
    with pytest.raises(ValueError, match="horizon"):
        SignNav3DEnv(horizon=0)
    with pytest.raises(ValueError, match="render_mode"):
        SignNav3DEnv(render_mode="human")
    env.reset(seed=0)
    for action in (4, -1, "left"):
        with pytest.raises(ValueError, match="action"):
            env.step(action)


@pytest.mark.opengl
def test_checkers_pass(env):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any checker warning fails the test
        check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True, skip_render_check=True)


@pytest.mark.opengl
def test_render():
    env = gym.make("SignNav3D-v0", render_mode="rgb_array")
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[1] >= 1280 and frame.shape[0] >= 480
        view = frame[:480, :640]
        assert np.array_equal(view[::8, ::8], env.unwrapped._inner_obs)  # the agent's own view, enlarged
    finally:
        env.close()


def test_missing_opengl_gives_a_clear_error(monkeypatch):
    # No EGL library: the engine import fails.
    def no_egl():
        raise ImportError('Library "EGL" not found.')

    monkeypatch.setattr(engine, "_ENGINE", None)
    monkeypatch.setattr(engine, "_import_engine", no_egl)
    with pytest.raises(OpenGLUnavailableError, match=r"needs OpenGL.*EGL.*libegl1") as excinfo:
        SignNav3DEnv()
    assert isinstance(excinfo.value, RuntimeError)
    assert isinstance(excinfo.value.__cause__, ImportError)

    # miniworld itself missing: say what to install.
    def no_miniworld():
        raise ModuleNotFoundError("No module named 'miniworld'", name="miniworld")

    monkeypatch.setattr(engine, "_import_engine", no_miniworld)
    with pytest.raises(ImportError, match="pip install"):
        SignNav3DEnv()


@pytest.mark.opengl
def test_gl_context_failure_gives_a_clear_error(env, monkeypatch):
    # The libraries load but no GL context can be made (e.g. no usable driver).
    pyglet = engine.load_engine().pyglet

    def no_context(*args, **kwargs):
        raise pyglet.gl.ContextException("Could not create GL context")

    monkeypatch.setattr(pyglet.window, "Window", no_context)
    with pytest.raises(OpenGLUnavailableError, match="Could not create GL context.*DISPLAY"):
        SignNav3DEnv()


@pytest.mark.opengl
@pytest.mark.parametrize("problem_id, instruction", [(BLUE, BALL), (BLUE, BOX), (RED, KEY), (RED, BOX)])
def test_oracle_reads_the_sign_and_scores_one(env, problem_id, instruction):
    oracle = dream_envs.make_oracle(env)
    result = play_trial(
        env,
        oracle,
        seed=problem_id * 10 + instruction[0],
        options={"problem_id": problem_id, "instruction": instruction},
    )
    assert oracle.colour == problem_id
    assert result["execution_returns"] == [1.0]
    assert result["exploration_length"] <= 19  # read, then ended exploration early


class SwapRedBlue(gym.ObservationWrapper):
    def observation(self, obs):
        return {**obs, "obs": obs["obs"][..., ::-1].copy()}


@pytest.mark.opengl
def test_oracle_reads_pixels_not_the_problem(env):
    """Shown images with red and blue swapped, the oracle misreads the sign and touches the wrong object."""
    oracle = env.oracle()
    result = play_trial(SwapRedBlue(env), oracle, seed=0, options={"problem_id": BLUE, "instruction": BOX})
    assert oracle.colour == RED and result["execution_returns"] == [-1.0]


@pytest.mark.opengl
def test_oracle_many_trials():
    n_exec = 2
    multi = SignNav3DEnv(n_exec_episodes=n_exec)
    try:
        oracle = multi.oracle()
        returns = [play_trial(multi, oracle, seed=seed)["execution_returns"] for seed in range(6)]
    finally:
        multi.close()
    assert np.all(np.array(returns) == 1.0)


@pytest.mark.opengl
def test_sign_pixels_counts_the_letters_in_view_and_restores_the_view(env):
    env.reset(seed=0, options={"problem_id": RED})
    front = view_from(env, SIGN_CENTER[0] - 2.5, SIGN_CENTER[2], 0.0)
    assert env.sign_pixels() > 100
    assert env._world.sign.shown == RED and np.array_equal(env._world.render_obs(), front)
    view_from(env, SIGN_CENTER[0] - 2.5, SIGN_CENTER[2], math.pi)  # back to the sign
    assert env.sign_pixels() == 0
    view_from(env, 5.0, 4.0, math.pi / 2)  # the top room, facing north
    assert env.sign_pixels() == 0


class EndExploration(ScriptedAgent):
    """Ends every inner episode at once: its explorations see only the start."""

    def act(self, obs, info):
        return END_EPISODE


@pytest.mark.opengl
def test_exploration_report_tells_reading_explorers_from_idle_ones(env):
    reading = sign_nav.exploration_report(env, env.oracle(), n_trials=4, seed=3)
    assert reading.sign_seen.all() and reading.past_barrier.all()
    assert (reading.sign_pixels > 100).all() and (reading.execution_returns == 1.0).all()
    assert "sign read (>= 20 pixels of its letters in a view) in 100% of explorations" in reading.summary()

    idle = sign_nav.exploration_report(env, EndExploration(), n_trials=4, seed=3)
    assert (idle.sign_pixels == 0).all() and not idle.past_barrier.any()
    assert (idle.exploration_lengths == 1).all() and (idle.execution_returns == 0.0).all()
    assert "in 0% of explorations" in idle.summary() and "not read: 0.000 (4 trials)" in idle.summary()

    with pytest.raises(ValueError, match="SignNav3D-v0"):
        sign_nav.exploration_report(gym.make("MetaBandit-v0"), EndExploration(), n_trials=1)
    with pytest.raises(ValueError, match="min_pixels"):
        sign_nav.exploration_report(env, EndExploration(), n_trials=1, min_pixels=0)


class TurnInPlace(ScriptedAgent):
    """Turns left forever: every inner episode runs into the horizon without touching anything."""

    def act(self, obs, info):
        return TURN_LEFT


class TouchRedBall(ScriptedAgent):
    """Ends exploration at once; in execution, is put next to the red ball and walks into it."""

    def __init__(self, env):
        self.env = env

    def act(self, obs, info):
        if int(obs["phase"]) == 0:
            return END_EPISODE
        place_before(self.env, "ball", "red")
        return MOVE_FORWARD


@pytest.mark.opengl
def test_exploration_report_tells_how_each_execution_episode_ended(env):
    # 6 trials pinned to every (problem, instruction): each target once, in EXECUTION_TARGETS' order
    pins = dict(problem_ids=[0, 0, 0, 1, 1, 1], instructions=[[1], [2], [3], [1], [2], [3]])
    oracle = sign_nav.exploration_report(env, env.oracle(), n_trials=6, seed=3, **pins)
    assert list(oracle.execution_targets) == list(range(6))
    assert list(oracle.outcome_counts()) == list(sign_nav.EXECUTION_TARGETS)
    assert all(
        counts == {"right": 1, "wrong": 0, "ended": 0, "timed out": 0} for counts in oracle.outcome_counts().values()
    )
    assert "execution by target (right/wrong/ended/timed out): blue ball 1/0/0/0, blue key 1/0/0/0" in oracle.summary()

    idle = sign_nav.exploration_report(env, EndExploration(), n_trials=6, seed=3, **pins)
    assert (idle.execution_outcomes == sign_nav.EXECUTION_OUTCOMES.index("ended")).all()
    turning = sign_nav.exploration_report(env, TurnInPlace(), n_trials=2, seed=3, **pins)
    assert (turning.execution_outcomes == sign_nav.EXECUTION_OUTCOMES.index("timed out")).all()
    assert "blue ball 0/0/0/1, blue key 0/0/0/1" in turning.summary()

    # a wrong touch: the red ball, which is the target only of (red, ball)
    wrong = sign_nav.exploration_report(env, TouchRedBall(env), n_trials=2, seed=3, **pins)
    assert "blue ball 0/1/0/0, blue key 0/1/0/0" in wrong.summary()


@pytest.mark.opengl
def test_public_info_has_no_problem(env):
    _, info = env.reset(seed=0)
    assert "problem_id" not in public_info(info)


def test_importing_needs_no_opengl():
    """The engine (pyglet, miniworld) is imported only when an env is built."""
    code = "import sys, dream_envs.sign_nav; assert 'pyglet' not in sys.modules and 'miniworld' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_without_opengl_the_cli_lists_sign_nav_as_unavailable_and_the_rest(monkeypatch, capsys):
    import dream_envs.__main__ as cli

    monkeypatch.setattr(cli, "opengl_available", lambda: (False, "no EGL library"))
    monkeypatch.setattr("sys.argv", ["dream_envs", "--trials", "1"])
    cli.main()
    rows = capsys.readouterr().out.splitlines()[1:]
    assert [row.split()[0] for row in rows] == [env_id for env_id, _ in cli.DEFAULT_VARIANTS]
    (sign_row,) = [row for row in rows if row.startswith("SignNav3D-v0")]
    assert sign_row.endswith("unavailable: no EGL library")
    assert all(row.count("±") == 2 for row in rows if row is not sign_row)  # the others were played


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="an unreachable X display fails this way on Linux")
def test_without_opengl_the_sign_nav_tests_skip_with_the_reason():
    # An unreachable X display: the engine loads but no GL context can be made.
    env = {**os.environ, "DISPLAY": ":987", "PYOPENGL_PLATFORM": ""}
    check = "from dream_envs.sign_nav import opengl_available as a; ok, why = a(); assert not ok and 'DISPLAY' in why"
    subprocess.run([sys.executable, "-c", check], env=env, check=True)
    out = subprocess.run(
        [sys.executable, "-m", "pytest", __file__, "-q", "-rs", "-p", "no:cacheprovider", "-k", "not without_opengl"],
        env=env,
        capture_output=True,
        text=True,
    ).stdout
    assert "failed" not in out and "error" not in out.lower().replace("openglunavailableerror", ""), out
    assert "needs OpenGL" in out and "SKIPPED" in out, out
