"""sb3_dream.presets: the named hyperparameter sets are valid DREAM arguments and say what they say."""

import copy

from sb3_dream import DREAM, PRESETS
from sb3_dream.experiments import RunConfig, make_model


def test_laptop_is_fast_plus_the_recurrent_whole_episode_execution():
    laptop = PRESETS["laptop"]
    assert {k: v for k, v in laptop.items() if k in PRESETS["fast"]} == PRESETS["fast"]
    assert laptop["execution_sampling"] == "episodes"
    assert laptop["policy_kwargs"] == {"execution_hidden_sizes": (128, 128), "execution_recurrent": True}


def test_every_preset_builds_a_model_and_is_not_changed_by_it():
    before = copy.deepcopy(PRESETS)
    for name, preset in PRESETS.items():
        model = DREAM("MetaBus-v0", **preset, buffer_size=20, execution_buffer_size=20)
        for key, value in preset.items():
            if key != "policy_kwargs":
                assert getattr(model, key) == value, (name, key)
    assert PRESETS == before  # a model keeps no reference that it could change


def test_laptop_builds_a_recurrent_wide_execution_network_and_the_runner_takes_it_by_name():
    model = make_model("dream", "MetaBus-v0", RunConfig(preset="laptop", dream_kwargs=(("buffer_size", 20),)), seed=0)
    execution = model.policy.execution_q
    assert execution.recurrent and model.execution_sampling == "episodes"
    hidden = [m.out_features for m in execution.modules() if m.__class__.__name__ == "Linear"]
    assert hidden.count(128) >= 2  # the (128, 128) body
