"""RL²'s recurrent dueling Q-network (paper, Appendix B.3), the history encoder it shares, and its SB3 policy."""

from __future__ import annotations

import copy
from typing import Any, ClassVar, Dict, List, Optional, Sequence, Tuple, Type

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_dream.common.embedders import TRIAL_KEYS, TrialInputEmbedder, check_trial_observation_space
from sb3_dream.common.optim import default_optimizer_kwargs
from sb3_dream.common.recurrent import DuelingHead, LSTMStates, reset_lstm_states, unroll_lstm, zero_lstm_states


class HistoryQNetwork(nn.Module):
    """RL²'s history encoder e(tau_:t), with the Q-values read from it left to a subclass.

    Per-step input (:class:`~sb3_dream.common.embedders.TrialInputEmbedder`): state ``obs`` (64, or
    128 for images), instruction (64), previous action (16), previous reward (16, linear),
    episode-start flag (16), concatenated -> linear ``fusion_dim`` + ReLU -> LSTM. A subclass adds
    the modules its :meth:`q_values` reads and nothing else: RL² reads the LSTM output alone
    (:class:`RL2QNetwork`), IMPORT and VariBAD read it with the current state
    (:class:`sb3_dream.common.conditioned.ConditionedQNetwork`).

    :param observation_space: a Dict space with at least ``obs``.
    :param fusion_dim: the linear layer over the concatenated embeddings (paper: 64).
    :param lstm_hidden_size: the LSTM's size (paper: 64).
    :param n_lstm_layers: stacked LSTM layers (paper: 1).
    :param embed_keys: which observation keys to embed when present.
    :param embed_kwargs: sizes for :class:`~sb3_dream.common.embedders.TrialInputEmbedder`.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        fusion_dim: int = 64,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 1,
        embed_keys: Sequence[str] = TRIAL_KEYS,
        embed_kwargs: Optional[Dict[str, Any]] = None,
    ) -> None:
        super().__init__()
        self.embedder = TrialInputEmbedder(observation_space, keys=embed_keys, **(embed_kwargs or {}))
        self.fusion = nn.Sequential(nn.Linear(self.embedder.embed_dim, fusion_dim), nn.ReLU())
        self.lstm = nn.LSTM(fusion_dim, lstm_hidden_size, num_layers=n_lstm_layers, batch_first=True)
        self.n_lstm_layers, self.lstm_hidden_size = n_lstm_layers, lstm_hidden_size

    def initial_states(self, batch: int, device: th.device | str = "cpu") -> LSTMStates:
        return zero_lstm_states(self.n_lstm_layers, batch, self.lstm_hidden_size, device)

    def encode(
        self,
        obs: Dict[str, th.Tensor],
        states: LSTMStates,
        burn_in: int = 0,
        burn_in_mask: Optional[th.Tensor] = None,
    ) -> Tuple[th.Tensor, LSTMStates]:
        """The history embedding e(tau_:t) of whole sequences (the LSTM's output), fused over time:
        ``obs[k]`` ``[B, T, ...]`` -> ``[B, T, lstm_hidden_size]``."""
        x = self.fusion(self.embedder(obs))
        return unroll_lstm(self.lstm, x, states, burn_in, burn_in_mask)

    def encode_step(self, obs: Dict[str, th.Tensor], states: LSTMStates) -> Tuple[th.Tensor, LSTMStates]:
        """:meth:`encode` for one step of a batch of envs: ``obs[k]`` ``[N, ...]`` -> ``[N, hidden]``."""
        x = self.fusion(self.embedder(obs)).unsqueeze(1)
        out, next_states = self.lstm(x, states)
        return out.squeeze(1), next_states

    def q_values(self, obs: Dict[str, th.Tensor], history: th.Tensor) -> th.Tensor:
        """Q-values from the history embedding (``[..., hidden]`` -> ``[..., A]``) and, as the
        subclass needs, the current step's ``obs``."""
        raise NotImplementedError

    def forward(
        self,
        obs: Dict[str, th.Tensor],
        states: LSTMStates,
        burn_in: int = 0,
        burn_in_mask: Optional[th.Tensor] = None,
    ) -> Tuple[th.Tensor, LSTMStates]:
        """Q-values of whole sequences, fused over time: ``obs[k]`` ``[B, T, ...]`` -> ``[B, T, A]``."""
        out, states = self.encode(obs, states, burn_in, burn_in_mask)
        return self.q_values(obs, out), states

    def step(
        self, obs: Dict[str, th.Tensor], states: LSTMStates, episode_start: th.Tensor
    ) -> Tuple[th.Tensor, LSTMStates, LSTMStates]:
        """One step for a batch of envs: ``obs[k]`` ``[N, ...]`` -> Q ``[N, A]``.

        The states of the envs whose *trial* starts (``episode_start``, ``[N]``) are zeroed first;
        the inner episodes' ``episode_start`` observation key never resets them.
        Returns ``(q, input_states, next_states)``; ``input_states`` are the (reset) states used.
        """
        states = reset_lstm_states(states, episode_start)
        out, next_states = self.encode_step(obs, states)
        return self.q_values(obs, out), states, next_states


class RL2QNetwork(HistoryQNetwork):
    """Q(s_t, i, tau_:t, a) of RL²: per-step embeddings -> linear 64 + ReLU -> LSTM 64 -> dueling head.

    The history encoder is :class:`HistoryQNetwork`'s; the head reads its output alone.

    :param n_actions: number of discrete actions.
    :param dueling: dueling head (paper) or a single linear Q head.
    The other parameters are :class:`HistoryQNetwork`'s.
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
    ) -> None:
        super().__init__(observation_space, fusion_dim, lstm_hidden_size, n_lstm_layers, embed_keys, embed_kwargs)
        # built after the encoder, as it always was: the same random draws, in the same order
        self.head: nn.Module = (
            DuelingHead(lstm_hidden_size, n_actions) if dueling else nn.Linear(lstm_hidden_size, n_actions)
        )

    def q_values(self, obs: Dict[str, th.Tensor], history: th.Tensor) -> th.Tensor:
        """Q-values from the history embedding alone (``[..., hidden]`` -> ``[..., A]``)."""
        return self.head(history)


class RL2DQNPolicy(BasePolicy):
    """Policy of :class:`~sb3_dream.rl2dqn.RL2DQN`: an online and a target :class:`RL2QNetwork`.

    ``predict(observation, state, episode_start, deterministic)`` follows sb3-contrib's recurrent
    convention: ``state`` is the LSTM's ``(h, c)`` as numpy arrays ``[n_layers, n_envs, hidden]``
    (``None`` = zeros), ``episode_start`` (``[n_envs]``) zeroes the state of envs whose trial starts.
    It is greedy; epsilon-greedy exploration lives in ``RL2DQN.predict``.

    :param observation_space: a Dict space with at least an ``obs`` key (see
        :func:`~sb3_dream.common.embedders.check_trial_observation_space`).
    :param action_space: Discrete.
    :param lr_schedule: learning-rate schedule (the initial value sets Adam's lr).
    :param optimizer_kwargs: Adam runs fused (``fused=True``) unless they set ``fused`` or
        ``foreach`` (:func:`~sb3_dream.common.optim.default_optimizer_kwargs`).
    :param network_kwargs: further arguments of :attr:`q_network_class` (a subclass's Q-network).
    """

    #: the Q-network class (a :class:`HistoryQNetwork`) built twice: online and target
    q_network_class: ClassVar[Type[HistoryQNetwork]] = RL2QNetwork
    action_space: spaces.Discrete
    observation_space: spaces.Dict

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        fusion_dim: int = 64,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 1,
        dueling: bool = True,
        embed_keys: Sequence[str] = TRIAL_KEYS,
        embed_kwargs: Optional[Dict[str, Any]] = None,
        normalize_images: bool = True,
        optimizer_class: Type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: Optional[Dict[str, Any]] = None,
        **network_kwargs: Any,
    ) -> None:
        self.check_spaces(observation_space, action_space)
        super().__init__(
            observation_space,
            action_space,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )
        self.net_kwargs = dict(
            fusion_dim=fusion_dim,
            lstm_hidden_size=lstm_hidden_size,
            n_lstm_layers=n_lstm_layers,
            dueling=dueling,
            embed_keys=tuple(embed_keys),
            embed_kwargs=dict(embed_kwargs or {}),
            **network_kwargs,
        )
        self._build_networks(
            observation_space,
            int(action_space.n),
            {
                **self.net_kwargs,
                "embed_kwargs": {"normalize_images": normalize_images, **self.net_kwargs["embed_kwargs"]},
            },
        )
        self.optimizer_kwargs = default_optimizer_kwargs(optimizer_class, self.optimizer_kwargs)
        self.optimizer = self.optimizer_class(self.trained_parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _build_networks(self, observation_space: spaces.Dict, n_actions: int, network_kwargs: Dict[str, Any]) -> None:
        """Build the online Q-network and its target from ``network_kwargs`` (the policy's network
        arguments). A hook: a subclass may take its own arguments out of ``network_kwargs`` and
        build further modules, which :meth:`trained_parameters` then lists."""
        self.q_net = self.q_network_class(observation_space, n_actions, **network_kwargs)
        self.q_net_target = copy.deepcopy(self.q_net)
        self.q_net_target.load_state_dict(self.q_net.state_dict())
        self.q_net_target.train(False)
        self.q_net_target.requires_grad_(False)

    def trained_parameters(self) -> List[nn.Parameter]:
        """The parameters the optimizer steps and the update clips: the online Q-network's (a
        subclass adds those of the modules it builds besides the Q-networks)."""
        return list(self.q_net.parameters())

    @classmethod
    def check_spaces(cls, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        """Raise ``ValueError`` unless the spaces suit this policy."""
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"action_space must be gymnasium.spaces.Discrete, got {action_space}")
        check_trial_observation_space(observation_space)

    @property
    def lstm_state_shape(self) -> Tuple[int, int]:
        return self.q_net.n_lstm_layers, self.q_net.lstm_hidden_size

    def _get_constructor_parameters(self) -> Dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                lr_schedule=self._dummy_schedule,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                **self.net_kwargs,
            )
        )
        return data

    def set_training_mode(self, mode: bool) -> None:
        if self.training == mode and self.q_net.training == mode:
            return  # called at every env step: skip walking the module tree
        self.q_net.train(mode)
        self.training = mode

    def forward(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self._predict(obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        """Greedy actions from a *fresh* state (one step, no memory): use :meth:`predict` to act."""
        assert isinstance(observation, dict)
        n = observation["obs"].shape[0]
        es = th.ones(n, device=self.device)
        q, _, _ = self.q_net.step(observation, self.q_net.initial_states(n, self.device), es)
        return q.argmax(dim=-1)

    def obs_to_states(self, state: Optional[Tuple[np.ndarray, ...]], n_envs: int) -> LSTMStates:
        """Numpy ``(h, c)`` (or ``None``) -> tensors on the policy's device, checked."""
        if state is None:
            return self.q_net.initial_states(n_envs, self.device)
        expected = (self.q_net.n_lstm_layers, n_envs, self.q_net.lstm_hidden_size)
        if not isinstance(state, (tuple, list)) or len(state) != 2:
            raise ValueError(
                f"state must be None or the LSTM's (h, c), each of shape {expected}; got {type(state).__name__}"
            )
        h, c = (th.as_tensor(np.asarray(s), dtype=th.float32, device=self.device) for s in state)
        if tuple(h.shape) != expected or tuple(c.shape) != expected:
            raise ValueError(
                f"state must be the LSTM's (h, c), each of shape {expected}; got {tuple(h.shape)}, {tuple(c.shape)}"
            )
        return h, c

    def predict(  # type: ignore[override]
        self,
        observation: Dict[str, np.ndarray],
        state: Optional[Tuple[np.ndarray, ...]] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
    ) -> Tuple[np.ndarray, Tuple[np.ndarray, np.ndarray]]:
        """Greedy action(s) and the next LSTM state (see the class docstring)."""
        self.set_training_mode(False)
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "predict() got a tuple (obs, info): pass the observation only (Gymnasium's reset() returns both)"
            )
        if not isinstance(observation, dict):
            raise ValueError(
                f"observation must be a dict with keys {sorted(self.observation_space.spaces)}, "
                f"got {type(observation).__name__}"
            )
        missing = set(self.observation_space.spaces) - set(observation)
        if missing:
            raise ValueError(f"observation is missing the keys {sorted(missing)}")
        obs_tensor, vectorized = self.obs_to_tensor(observation)
        n_envs = int(obs_tensor["obs"].shape[0])
        states = self.obs_to_states(state, n_envs)
        if episode_start is None:
            es = th.zeros(n_envs, device=self.device)
        else:
            es_np = np.asarray(episode_start, dtype=np.float32).reshape(-1)
            if es_np.shape[0] != n_envs:
                raise ValueError(
                    f"episode_start must have one entry per env ({n_envs}), got shape {np.shape(episode_start)}"
                )
            es = th.as_tensor(es_np, device=self.device)
        with th.no_grad():
            q, _, (h, c) = self.q_net.step(obs_tensor, states, es)
        actions = q.argmax(dim=-1).cpu().numpy()
        if not vectorized:
            actions = actions.squeeze(axis=0)
        return actions, (h.cpu().numpy(), c.cpu().numpy())


class MultiInputLstmPolicy(RL2DQNPolicy):
    """:class:`RL2DQNPolicy` for Dict observations (the default: grid trial envs)."""


class CnnLstmPolicy(RL2DQNPolicy):
    """:class:`RL2DQNPolicy` whose ``obs`` key must be an image (uint8 HxWxC or CxHxW): the CNN embedder."""

    @classmethod
    def check_spaces(cls, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        super().check_spaces(observation_space, action_space)
        assert isinstance(observation_space, spaces.Dict)
        space = observation_space.spaces["obs"]
        if not is_image_space(space, check_channels=False):
            raise ValueError(
                f"CnnLstmPolicy needs an image observation_space['obs'] (uint8 Box, HxWxC or CxHxW), got {space}; "
                "use MultiInputLstmPolicy"
            )
