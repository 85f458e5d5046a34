"""Rewrite a saved model (DREAM, RL2DQN, IMPORT or VariBAD) without its optimizers' moment estimates.

    python models/slim.py dream_map.zip models/dream_metabus_map.zip

``model.save`` stores the networks (with their target copies) and each Adam optimizer's state,
which holds two moment estimates per parameter: half of a DREAM zip. Acting, meta-testing and
watching need none of it, so the shipped models keep the networks exactly and the optimizers'
settings with an empty state (training further from such a file starts Adam's moments afresh).
A saved model never holds a replay buffer (that is ``save_replay_buffer``).
"""

from __future__ import annotations

import argparse
import os
from functools import reduce
from typing import Any

import torch as th

from sb3_dream.loading import load_model


def slim(source: str, target: str) -> Any:
    """Load ``source``, empty its optimizers' states, save it to ``target``; return the model."""
    model = load_model(source, device="cpu")
    names, _ = model._get_torch_save_params()
    for name in names:
        obj = reduce(getattr, name.split("."), model)
        if isinstance(obj, th.optim.Optimizer):
            obj.state.clear()
    os.makedirs(os.path.dirname(os.path.abspath(target)), exist_ok=True)
    model.save(target)
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="a model saved by model.save")
    parser.add_argument("target", help="where to write the slim copy")
    args = parser.parse_args()
    slim(args.source, args.target)
    print(
        f"{args.target}: {os.path.getsize(args.target) / 1e6:.2f} MB (was {os.path.getsize(args.source) / 1e6:.2f} MB)"
    )


if __name__ == "__main__":
    main()
