"""sb3_dream.evaluation: meta-test trials for scripted agents and SB3-style models."""

from __future__ import annotations

import numpy as np
import pytest

import dream_envs
from dream_envs import RandomAgent
from sb3_dream.common.agents import PolicyAgent, PolicyBatchAgent
from sb3_dream.evaluation import MetaEvalCallback, MetaEvalResult, as_trial_agent, evaluate_meta, privileged_trials


class FirstActionModel:
    """A model whose predict plays the bandit's a_* in exploration, then action 1; records its calls
    (each env's ``episode_start`` and the state it was given: the step within the trial)."""

    def __init__(self):
        self.calls = []

    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        starts = np.asarray(episode_start, dtype=bool)
        self.calls.append((starts.tolist(), None if state is None else state.tolist()))
        step = np.zeros(len(starts), int) if state is None else np.where(starts, 0, state + 1)
        return (np.asarray(obs["phase"]).reshape(len(starts)) == 1).astype(int), step


def test_oracle_is_optimal_and_random_is_chance_on_the_bandit():
    oracle = dream_envs.make_oracle(__import__("gymnasium").make("MetaBandit-v0", n_actions=4))
    best = evaluate_meta(oracle, "MetaBandit-v0", n_trials=40, n_exec_episodes=3, env_kwargs={"n_actions": 4})
    assert best.returns.shape == (40, 3) and best.mean == 1.0 and best.ci == 0.0
    assert best.mean_exploration_length == 1.0
    rand = evaluate_meta(
        RandomAgent(__import__("gymnasium").spaces.Discrete(4), seed=0),
        "MetaBandit-v0",
        n_trials=400,
        env_kwargs={"n_actions": 4},
    )
    assert abs(rand.mean - 0.25) < 2 * rand.ci + 0.02 and rand.ci > 0


def test_policy_agent_carries_state_within_a_trial_and_resets_between():
    model = FirstActionModel()
    kwargs = {"n_actions": 2}
    result = evaluate_meta(model, "MetaBandit-v0", n_trials=4, n_exec_episodes=2, env_kwargs=kwargs, n_envs=1)
    assert model.calls == [([True], None), ([False], [0]), ([False], [1])] * 4
    # action 1 is right exactly in problem 1
    np.testing.assert_array_equal(result.returns[:, 0], (result.problem_ids == 1).astype(float))


def test_trials_side_by_side_reset_each_env_state_at_its_own_trial_start():
    model = FirstActionModel()
    kwargs = {"n_actions": 2}
    result = evaluate_meta(model, "MetaBandit-v0", n_trials=5, n_exec_episodes=2, env_kwargs=kwargs, n_envs=2)
    # trials 0-1, then 2-3, then 4 in the first env, the second idle (its action ignored)
    starts = [[True, True], [False, False], [False, False]] * 2 + [[True, False], [False, False], [False, False]]
    assert [s for s, _ in model.calls] == starts
    # the state given: each trial's step counter, reset in an env where its next trial starts
    assert [state for _, state in model.calls[2:5]] == [[1, 1], [2, 2], [0, 0]]
    assert [state for _, state in model.calls[5:8]] == [[1, 1], [2, 2], [0, 3]]
    np.testing.assert_array_equal(result.returns[:, 0], (result.problem_ids == 1).astype(float))
    one_by_one = evaluate_meta(FirstActionModel(), "MetaBandit-v0", 5, n_exec_episodes=2, env_kwargs=kwargs, n_envs=1)
    np.testing.assert_array_equal(result.problem_ids, one_by_one.problem_ids)
    # a batch agent given as such plays one trial at a time in a single env
    batch_agent = PolicyBatchAgent(FirstActionModel())
    alone = evaluate_meta(batch_agent, "MetaBandit-v0", 5, n_exec_episodes=2, env_kwargs=kwargs, n_envs=1)
    np.testing.assert_array_equal(result.returns, alone.returns)
    assert batch_agent.model.calls[0] == ([True], None)


def test_pinned_problem_ids_cycle():
    result = evaluate_meta(
        FirstActionModel(), "MetaBandit-v0", n_trials=6, problem_ids=[0, 1], env_kwargs={"n_actions": 2}
    )
    assert result.problem_ids.tolist() == [0, 1] * 3 and result.returns[:, 0].tolist() == [0.0, 1.0] * 3


def test_result_statistics():
    r = MetaEvalResult(np.array([[1.0, 0.0], [0.0, 0.0]]), np.array([2.0, 4.0]), np.array([0, 1]), 0.1)
    assert r.mean == 0.25 and r.per_episode_mean.tolist() == [0.5, 0.0] and r.mean_exploration_length == 3.0
    assert r.per_episode_ci[1] == 0.0 and r.per_episode_ci[0] > 0 and "0.250" in r.summary()
    # A wrong choice (-1) and no choice (0) are told apart: one episode of four each above and below.
    signed = MetaEvalResult(np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([2.0, 4.0]), np.array([0, 1]), 0.1)
    assert signed.mean == 0.0 and signed.return_shares() == (0.25, 0.25, 0.5)
    # Exhaustive: each trial weighs its pair's probability (0.75, 0.25).
    weighted = MetaEvalResult(np.array([[1.0], [-1.0]]), np.zeros(2), np.array([0, 1]), 0.1, np.array([0.75, 0.25]))
    assert weighted.return_shares() == (0.75, 0.25, 0.0)


def test_bad_input():
    with pytest.raises(TypeError, match="agent"):
        as_trial_agent(object())
    with pytest.raises(ValueError, match="split"):
        evaluate_meta(FirstActionModel(), "MetaBandit-v0", split="val")
    with pytest.raises(ValueError, match="n_trials"):
        evaluate_meta(FirstActionModel(), "MetaBandit-v0", n_trials=0)
    import gymnasium as gym

    with pytest.raises(ValueError, match="split"):
        evaluate_meta(FirstActionModel(), gym.make("MetaBandit-v0", split="train"), split="test")
    # A split of another family is named with this env's accepted values.
    with pytest.raises(ValueError, match="split='test_problems' is not valid; accepted values: 'train', 'test', 'all'"):
        evaluate_meta(FirstActionModel(), "MetaBandit-v0", split="test_problems")
    with pytest.raises(ValueError, match="split='test_problems' is not valid"):
        evaluate_meta(FirstActionModel(), gym.make("MetaBandit-v0"), split="test_problems")
    assert evaluate_meta(FirstActionModel(), "MetaCook-v0", n_trials=2, split="test_problems").n_trials == 2
    assert isinstance(as_trial_agent(FirstActionModel()), PolicyAgent)
    with pytest.raises(ValueError, match="n_envs"):
        evaluate_meta(FirstActionModel(), "MetaBandit-v0", n_envs=0)
    with pytest.raises(ValueError, match="n_envs"):
        MetaEvalCallback("MetaBandit-v0", n_envs=0)
    with pytest.raises(ValueError, match="best_ties='latest' is not valid; accepted values: 'first', 'last'"):
        MetaEvalCallback("MetaBandit-v0", best_ties="latest")
    with pytest.raises(ValueError, match="log_prefix must be a non-empty string such as 'eval/', got ''"):
        MetaEvalCallback("MetaBandit-v0", log_prefix="")
    with pytest.raises(ValueError, match="env must not be an empty list"):
        evaluate_meta(FirstActionModel(), [])
    with pytest.raises(ValueError, match="split"):
        evaluate_meta(FirstActionModel(), [gym.make("MetaBandit-v0", split="train")] * 2, split="test")


@pytest.mark.parametrize("ties, expected", [("first", 100), ("last", 300)])
def test_best_ties_choose_among_equal_best_evaluations(ties, expected):
    """A learning curve that reaches its best twice: SB3's rule keeps the first, ``last`` the latest."""
    callback = MetaEvalCallback("MetaBandit-v0", n_trials=2, n_envs=1, best_ties=ties)
    curve = [(0, -1.0), (100, 0.5), (200, 0.2), (300, 0.5), (400, 0.4)]
    callback.resume([{"env_steps": k, "wall_clock_s": 0.0, "mean": m, "ci": 0.0, "exploration_length": 1.0}
                     for k, m in curve])  # fmt: skip
    assert (callback.best_env_steps, callback.best_mean_reward) == (expected, 0.5)
    assert callback._is_best(0.5) is (ties == "last") and callback._is_best(0.6) and not callback._is_best(0.4)


def test_exhaustive_evaluation_is_the_splits_expected_return():
    """On MetaCook's held-out split the oracle's exhaustive mean is the probability-weighted optimal
    return of every (problem, recipe) pair, to rounding: the split's expected return itself."""
    import gymnasium as gym

    from dream_envs.cook import optimal_execution_return

    env = gym.make("MetaCook-v0", split="test")
    pids, instructions, probabilities = env.unwrapped.trial_cases()
    expected = sum(p * optimal_execution_return(int(k), tuple(i)) for k, i, p in zip(pids, instructions, probabilities))
    result = evaluate_meta(dream_envs.make_oracle(env), env, n_trials=100, exhaustive=True)
    assert result.exhaustive and result.n_trials == len(pids) == 133  # one whole pass covers 100 trials
    assert result.problem_ids.tolist() == pids.tolist()
    assert result.mean == pytest.approx(expected, abs=1e-9) and np.isnan(result.ci)  # one pass: no spread measured
    assert np.isclose(result.trial_weights.sum(), 1.0) and "133 (problem, instruction) pairs" in result.summary()
    # the training split weights its pairs differently from a plain mean over them
    train = evaluate_meta(dream_envs.make_oracle(env), "MetaCook-v0", split="train", n_trials=1, exhaustive=True)
    assert train.n_trials == 2268 and abs(train.mean - train.returns.mean()) > 1e-3


def test_exhaustive_evaluation_plays_whole_passes_and_measures_their_spread():
    kwargs = {"n_actions": 2}  # 2 problems of one instruction each
    result = evaluate_meta(FirstActionModel(), "MetaBandit-v0", n_trials=5, env_kwargs=kwargs, exhaustive=True)
    assert result.problem_ids.tolist() == [0, 1] * 3 and result.n_trials == 6  # 5 trials: 3 whole passes
    # the model is deterministic: no spread between passes, so the half-width is 0
    assert result.mean == 0.5 and result.ci == 0.0
    one_by_one = evaluate_meta(FirstActionModel(), "MetaBandit-v0", 5, env_kwargs=kwargs, exhaustive=True, n_envs=1)
    np.testing.assert_array_equal(one_by_one.returns, result.returns)
    rand = evaluate_meta(
        RandomAgent(__import__("gymnasium").spaces.Discrete(2), seed=0),
        "MetaBandit-v0",
        n_trials=400,
        env_kwargs=kwargs,
        exhaustive=True,
    )
    assert rand.n_trials == 400 and rand.ci > 0 and abs(rand.mean - 0.5) < 2 * rand.ci + 0.02


def test_exhaustive_bad_input():
    import gymnasium as gym

    with pytest.raises(ValueError, match="problem_ids and exhaustive"):
        evaluate_meta(FirstActionModel(), "MetaBandit-v0", problem_ids=[0], exhaustive=True)

    from dream_envs.bandit import MetaBanditEnv

    class DrawnBandit(MetaBanditEnv):  # draws its instruction without listing the choices
        _instruction_choices = dream_envs.TrialEnv._instruction_choices

        def _sample_instruction(self, problem_id, split):
            return np.array([1])

    assert evaluate_meta(FirstActionModel(), DrawnBandit(split="test"), n_trials=3).n_trials == 3
    with pytest.raises(ValueError, match="_instruction_choices"):
        evaluate_meta(FirstActionModel(), DrawnBandit(split="test"), exhaustive=True)
    with pytest.raises(ValueError, match="_instruction_choices"):
        MetaEvalCallback(DrawnBandit(split="test"), exhaustive=True)
    with pytest.raises(ValueError, match="instructions must come with problem_ids"):
        dream_envs.play_trials(gym.make("MetaBandit-v0"), RandomAgent(gym.spaces.Discrete(2)), 2, instructions=[[1]])


@pytest.mark.parametrize("exhaustive", [False, True])
def test_privileged_trials_play_the_same_pinned_trials_and_close_the_envs_they_made(monkeypatch, exhaustive):
    closed = []
    with privileged_trials("MetaCook-v0", 7, "test_problems", 3, None, None, 3, exhaustive) as trials:
        assert len(trials.made) == 3 and trials.envs == trials.made
        assert set(trials.problem_ids) <= set(trials.split_ids.tolist())
        for env in trials.made:
            monkeypatch.setattr(env, "close", lambda env=env: closed.append(env))
        oracle = dream_envs.make_oracle(trials.envs[0])
        first, second = trials.play(oracle), trials.play(oracle)
        assert not closed
    assert closed == trials.made
    np.testing.assert_array_equal(first.problem_ids, trials.problem_ids)
    np.testing.assert_array_equal(second.problem_ids, trials.problem_ids)
    np.testing.assert_array_equal(first.returns, second.returns)  # the oracle is deterministic
    assert len(trials.problem_ids) == (25 if exhaustive else 7)  # exhaustive: a whole pass of the 25 pairs


def test_privileged_trials_leave_a_given_env_open(monkeypatch):
    env = __import__("gymnasium").make("MetaBandit-v0", split="test")
    with privileged_trials(env, 4, "test", 0, None, None, 16) as trials:
        assert trials.envs == [env] and trials.made == []
        monkeypatch.setattr(env, "close", lambda: pytest.fail("closed an env the caller made"))
        trials.play(dream_envs.make_oracle(env))
