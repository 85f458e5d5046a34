"""sb3_dream.loading.load_model: a saved model of each algorithm loads without naming its class."""

import json
import zipfile

import numpy as np
import pytest
import torch as th

from sb3_dream import DREAM, IMPORT, RL2DQN, VariBAD
from sb3_dream.evaluation import evaluate_meta
from sb3_dream.loading import load_model, saved_algorithm

SMALL = {
    DREAM: dict(buffer_size=20, execution_buffer_size=50),
    RL2DQN: dict(buffer_size=20),
    IMPORT: dict(buffer_size=20),
    VariBAD: dict(buffer_size=20),
}


@pytest.mark.parametrize("cls", [DREAM, RL2DQN, IMPORT, VariBAD], ids=lambda c: c.__name__)
def test_each_algorithm_loads_as_itself_and_meta_tests_the_same(tmp_path, cls):
    model = cls("MetaBus-v0", seed=0, learning_starts=20, **SMALL[cls])
    model.learn(60)
    path = tmp_path / "model.zip"
    model.save(path)
    assert saved_algorithm(str(path)) is cls
    loaded = load_model(str(path))
    assert type(loaded) is cls
    saved, restored = model.policy.state_dict(), loaded.policy.state_dict()
    assert saved.keys() == restored.keys()
    assert all(th.equal(saved[name], restored[name]) for name in saved)
    kwargs = dict(split="test", n_trials=6, seed=3)
    np.testing.assert_array_equal(
        evaluate_meta(loaded, "MetaBus-v0", **kwargs).returns, evaluate_meta(model, "MetaBus-v0", **kwargs).returns
    )


def test_a_file_of_another_model_is_refused_naming_the_accepted_algorithms(tmp_path):
    path = tmp_path / "dqn.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", json.dumps({"policy_class": {"__module__": "stable_baselines3.dqn.policies"}}))
    with pytest.raises(ValueError, match=r"holds none of DREAM, RL2DQN, IMPORT, VariBAD .*stable_baselines3\.dqn"):
        load_model(str(path))
