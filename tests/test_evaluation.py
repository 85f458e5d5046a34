"""sb3_dream.evaluation: meta-test trials for scripted agents and SB3-style models."""

from __future__ import annotations

import numpy as np
import pytest

import dream_envs
from dream_envs import RandomAgent
from sb3_dream.evaluation import MetaEvalResult, PolicyAgent, as_trial_agent, evaluate_meta


class FirstActionModel:
    """A model whose predict plays the bandit's a_* in exploration, then action 1; records its calls."""

    def __init__(self):
        self.calls = []

    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        self.calls.append((bool(episode_start[0]), state))
        step = 0 if state is None else state + 1
        return np.array([1 if obs["phase"] == 1 else 0]), step


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
    result = evaluate_meta(model, "MetaBandit-v0", n_trials=4, n_exec_episodes=2, env_kwargs={"n_actions": 2})
    starts = [s for s, _ in model.calls]
    assert len(model.calls) == 4 * 3 and starts == [True, False, False] * 4
    assert [st for _, st in model.calls[:3]] == [None, 0, 1]
    # action 1 is right exactly in problem 1
    np.testing.assert_array_equal(result.returns[:, 0], (result.problem_ids == 1).astype(float))


def test_pinned_problem_ids_cycle():
    result = evaluate_meta(
        FirstActionModel(), "MetaBandit-v0", n_trials=6, problem_ids=[0, 1], env_kwargs={"n_actions": 2}
    )
    assert result.problem_ids.tolist() == [0, 1] * 3 and result.returns[:, 0].tolist() == [0.0, 1.0] * 3


def test_result_statistics():
    r = MetaEvalResult(np.array([[1.0, 0.0], [0.0, 0.0]]), np.array([2.0, 4.0]), np.array([0, 1]), 0.1)
    assert r.mean == 0.25 and r.per_episode_mean.tolist() == [0.5, 0.0] and r.mean_exploration_length == 3.0
    assert r.per_episode_ci[1] == 0.0 and r.per_episode_ci[0] > 0 and "0.250" in r.summary()


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
