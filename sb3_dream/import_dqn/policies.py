"""IMPORT's Q-network (Kamienny et al., 2020, as the DREAM paper's Appendix B.3 runs it) and its SB3 policies."""

from __future__ import annotations

from typing import Any, Dict, Optional, Sequence, Union

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_dream.common.conditioned import ConditionedQNetwork, ConditionedQPolicy
from sb3_dream.common.embedders import TRIAL_KEYS, MultiDiscreteEmbedder
from sb3_dream.rl2dqn.policies import CnnLstmPolicy as RL2CnnLstmPolicy


class IMPORTQNetwork(ConditionedQNetwork):
    """Q(s_t, i, z, a) with z either the problem embedding e(T) or the history embedding e(tau_:t).

    e(T) embeds the problem's features (``problem_nvec``, see
    :meth:`dream_envs.TrialEnv.problem_features`) like the paper's other problem-ID embedders: 32
    units per dimension, then 256 and ``lstm_hidden_size`` (paper: 64, the size of e(tau_:t)).

    :param problem_nvec: the sizes of the problem features (``env.unwrapped.trial_spec()["problem_nvec"]``).
    :param problem_per_dim: per-dimension embedding size of e(T) (paper: 32).
    :param problem_hidden_dim: e(T)'s hidden layer (paper: 256).
    The other parameters are :class:`~sb3_dream.common.conditioned.ConditionedQNetwork`'s.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        n_actions: int,
        fusion_dim: int = 64,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 1,
        dueling: bool = True,
        embed_keys: Sequence[str] = TRIAL_KEYS,
        embed_kwargs: Optional[Dict[str, Any]] = None,
        q_hidden_dim: Union[int, Sequence[int]] = 64,
        problem_nvec: Optional[Sequence[int]] = None,
        problem_per_dim: int = 32,
        problem_hidden_dim: int = 256,
    ) -> None:
        if problem_nvec is None or len(problem_nvec) == 0:
            raise ValueError(
                "problem_nvec is required: the sizes of the env's problem features (trial_spec()['problem_nvec'])"
            )
        super().__init__(
            observation_space,
            n_actions,
            fusion_dim,
            lstm_hidden_size,
            n_lstm_layers,
            dueling,
            embed_keys,
            embed_kwargs,
            q_hidden_dim,
        )
        # e(T) has z's size: it stands in for e(tau_:t) and is the auxiliary loss's target
        self.problem_embedder = MultiDiscreteEmbedder(
            np.asarray(problem_nvec, dtype=np.int64), problem_per_dim, (problem_hidden_dim, lstm_hidden_size)
        )

    def choose_z(self, history: th.Tensor, problem_features: th.Tensor, use_problem: th.Tensor) -> th.Tensor:
        """z of each sequence: e(T) where ``use_problem`` (``[B]``) is set, else e(tau_:t).

        :param history: ``[B, T, z_dim]`` or ``[B, z_dim]`` (one step).
        :param problem_features: ``[B, len(problem_nvec)]``.
        """
        if not bool(use_problem.any()):
            return history
        e_problem = self.problem_embedder(problem_features)  # [B, z]
        if history.dim() == 3:
            e_problem = e_problem.unsqueeze(1).expand_as(history)
        keep = use_problem.view(-1, *([1] * (history.dim() - 1))).bool()
        return th.where(keep, e_problem, history)


class IMPORTPolicy(ConditionedQPolicy):
    """Policy of :class:`~sb3_dream.import_dqn.IMPORT`: an online and a target :class:`IMPORTQNetwork`.

    ``predict`` (and so meta-testing) always acts on z = e(tau_:t): the problem ID never enters
    it. ``policy_kwargs`` may set the network's sizes (``q_hidden_dim``, ``problem_per_dim``, ...);
    IMPORT fills ``problem_nvec`` from the env.
    """

    q_network_class = IMPORTQNetwork


class MultiInputLstmPolicy(IMPORTPolicy):
    """:class:`IMPORTPolicy` for Dict observations (the default: grid trial envs)."""


class CnnLstmPolicy(IMPORTPolicy, RL2CnnLstmPolicy):
    """:class:`IMPORTPolicy` whose ``obs`` key must be an image (uint8 HxWxC or CxHxW): the CNN embedder."""
