"""Why do VARIBAD and IMPORT learn MetaCook more slowly than RL², with RL²'s history encoder?

VARIBAD without its decoder losses (``decoder_loss_coef=0``) is RL²'s encoder under VARIBAD's
Q-head: Q reads ``[e(s); e(i); z]`` (fresh embeddings of the state and instruction beside the
LSTM's output z) through one linear layer of 64 with ReLU, where RL²'s dueling head reads z alone.
On MetaCook that run learns the training split more slowly than every RL² seed
(docs/results/metacook.md, "Why IMPORT and VARIBAD learn MetaCook slowly"). This probe registers
the runner algorithm ``rl2dqn_relu_head``: RL²'s network with that one ReLU layer between the LSTM
and the dueling head and no fresh embeddings, so the two differences can be told apart:

* near RL²: the extra layer is harmless, and the fresh embeddings slow VARIBAD's head;
* near VARIBAD without its losses: the extra layer itself is what slows it.

Every other setting is RL2DQN's (``--preset``, ``--rl2dqn-kwargs``; the layer's size is
``--rl2dqn-kwargs "policy_kwargs={'head_hidden_dim':64}"``). The arguments are the experiment
runner's (``python -m sb3_dream.experiments --help``), for example::

    python research/cook_q_head_probe.py --envs MetaCook-v0 --algos rl2dqn_relu_head --seeds 0 \\
        --steps 200000 --n-envs 4 --preset fast --eval-freq 10000 --eval-trials 100 \\
        --eval-splits test train --select-on train --jobs 1 --threads 1 --out results/cook_q_head_probe
"""

from __future__ import annotations

import sys
from typing import Any

from gymnasium import spaces
from torch import nn

from sb3_dream import RL2DQN
from sb3_dream.common.recurrent import DuelingHead
from sb3_dream.experiments.algorithms import ALGORITHMS, AlgorithmSpec, register_algorithm
from sb3_dream.presets import RL2DQN_PRESETS
from sb3_dream.rl2dqn.policies import RL2DQNPolicy, RL2QNetwork

NAME = "rl2dqn_relu_head"


class ReluHeadQNetwork(RL2QNetwork):
    """RL²'s Q-network with one linear + ReLU layer of ``head_hidden_dim`` between the LSTM and the
    head (VARIBAD's head over z alone, without ``[e(s); e(i)]``)."""

    def __init__(
        self, observation_space: spaces.Dict, n_actions: int, head_hidden_dim: int = 64, **kwargs: Any
    ) -> None:
        super().__init__(observation_space, n_actions, **kwargs)
        out = (
            DuelingHead(head_hidden_dim, n_actions)
            if kwargs.get("dueling", True)
            else nn.Linear(head_hidden_dim, n_actions)
        )
        self.head = nn.Sequential(nn.Linear(self.lstm_hidden_size, head_hidden_dim), nn.ReLU(), out)


class ReluHeadPolicy(RL2DQNPolicy):
    """:class:`~sb3_dream.rl2dqn.policies.RL2DQNPolicy` over :class:`ReluHeadQNetwork`."""

    q_network_class = ReluHeadQNetwork


class ReluHeadRL2DQN(RL2DQN):
    """RL2DQN whose default policy is :class:`ReluHeadPolicy`."""

    policy_aliases = {**RL2DQN.policy_aliases, "MultiInputLstmPolicy": ReluHeadPolicy}


# Registered on import: the runner's worker processes import this module to find the algorithm.
if NAME not in ALGORITHMS:
    register_algorithm(AlgorithmSpec(NAME, lambda: ReluHeadRL2DQN, RL2DQN_PRESETS, "rl2dqn_kwargs"))


if __name__ == "__main__":
    from sb3_dream.experiments.cli import main

    main(sys.argv[1:])
