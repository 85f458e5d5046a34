"""DREAM's four networks (paper, Section 4.3 and Appendix B.3).

* :class:`ProblemEncoder` f_psi: problem ID -> z (the mean of F(z | T) = N(f(T), rho^2 I)).
* :class:`TrajectoryDecoder` g_omega: exploration trajectory tau^exp -> z, one fused LSTM pass
  giving g(tau_:t) for every prefix t = 0 .. T.
* :class:`ExecutionQNetwork` Q^exe(s, i, z): feed-forward dueling Q-network (optionally also given
  the step index within the execution episode, or recurrent over the execution episode).
* :class:`ExplorationQNetwork` Q^exp(s_t, tau_:t): recurrent dueling Q-network over its own history.

:class:`DreamPolicy` holds them and their target copies.
"""

from __future__ import annotations

import copy
from typing import Any, Dict, Optional, Sequence, Tuple, Type, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import polyak_update
from torch import nn

from dream_envs.checks import check_bool, check_layer_sizes, check_non_negative, check_positive_int
from sb3_dream.common.embedders import (
    DistinctFrames,
    ImageEmbedder,
    MultiDiscreteEmbedder,
    make_state_embedder,
    relu_mlp,
)
from sb3_dream.common.optim import default_optimizer_kwargs
from sb3_dream.common.recurrent import DuelingHead
from sb3_dream.dream.buffers import ExecutionBatch

LSTMState = Tuple[th.Tensor, th.Tensor]


def _frames_or(frames: Optional[DistinctFrames], states: th.Tensor) -> Union[th.Tensor, DistinctFrames]:
    """A batch's distinct image frames where it has them (each embedded once), else its states."""
    return states if frames is None else frames


def next_steps(batch: ExecutionBatch) -> th.Tensor:
    """The step of each s' of ``batch`` within its execution episode: the next one, or an n-step
    window's last state's."""
    return batch.steps + 1 if batch.next_steps is None else batch.next_steps


class ProblemEncoder(nn.Module):
    """f_psi(T): embeds each dimension of the problem's structured representation (Appendix B.3)."""

    def __init__(self, problem_nvec: np.ndarray, z_dim: int = 64) -> None:
        super().__init__()
        self.embed = MultiDiscreteEmbedder(problem_nvec, hidden_dims=(256,))
        # No activation on the output: z lives in all of R^d (the bottleneck bounds its norm).
        self.out = nn.Linear(256, z_dim)

    def forward(self, problem_features: th.Tensor) -> th.Tensor:
        return self.out(self.embed(problem_features))


class TrajectoryDecoder(nn.Module):
    """g_omega(tau^exp) for every prefix of tau^exp = (s_0, a_0, s_1, ..., s_T).

    Each transition (s_t, a_t, s_{t+1}) is embedded as [e(s_t); e(a_t); e(s_{t+1})] -> 128 -> 64
    (ReLU); an LSTM of ``hidden_size`` (the paper's 128) runs over the transitions; a zero "empty
    prefix" output is prepended so that one pass yields g(tau_:0) ... g(tau_:T); an MLP 128 -> z_dim
    maps each to z.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        n_actions: int,
        z_dim: int = 64,
        hidden_size: int = 128,
        image_downsample: int = 1,
    ) -> None:
        super().__init__()
        self.state_embed = make_state_embedder(observation_space, image_downsample=image_downsample)
        self.action_embed = nn.Embedding(n_actions, 32)
        d = self.state_embed.embed_dim
        self.transition = nn.Sequential(nn.Linear(2 * d + 32, 128), nn.ReLU(), nn.Linear(128, 64), nn.ReLU())
        self.lstm = nn.LSTM(64, hidden_size, batch_first=True)
        self.head = nn.Sequential(nn.Linear(hidden_size, 128), nn.ReLU(), nn.Linear(128, z_dim))

    def forward(
        self,
        states: Union[th.Tensor, DistinctFrames],
        actions: th.Tensor,
        lengths: Optional[th.Tensor] = None,
    ) -> th.Tensor:
        """``states`` [B, T+1, ...] (s_0 .. s_T, padded; image states may come as their
        :class:`~sb3_dream.common.embedders.DistinctFrames`), ``actions`` [B, T] -> g for prefixes
        [B, T+1, z].

        Prefix t's output only depends on the first t transitions, so padding after a trajectory's
        end never changes its valid prefixes. With ``lengths`` [B] (transitions in each trajectory)
        only g(tau_:length) is returned, [B, z]: the head then runs on those rows alone.
        """
        e = self.state_embed(states)  # embed each state once, shared by its two transitions
        x = self.transition(th.cat([e[:, :-1], self.action_embed(actions), e[:, 1:]], dim=-1))
        h, _ = self.lstm(x)
        h = th.cat([h.new_zeros(h.shape[0], 1, h.shape[2]), h], dim=1)
        if lengths is not None:
            h = h[th.arange(h.shape[0], device=h.device), lengths]
        return self.head(h)


class ExecutionQNetwork(nn.Module):
    """Q^exe(s, i, z, .): [e(s); e(i); z] -> Linear 64 + ReLU -> dueling head (Appendix B.3).

    ``hidden_sizes`` are the layers between the concatenation and the dueling head: the paper's
    ``(64,)`` by default; wider or deeper bodies are an option (the one layer is where the
    instruction and z must interact to pick, e.g., the right bus).

    ``time_steps`` > 0 (an option; the paper's network has no such input) adds e(t), a 16-d
    embedding of the step t within the execution episode (clipped to ``time_steps``), to
    [e(s); e(i)]. A feed-forward policy that revisits a state is caught in a loop until the horizon
    ends the episode; with t it can act differently on its second visit, e.g. try another bus
    after riding back from a wrong one when z leaves two buses possible. It also makes the
    horizon-terminal TD targets Markov (the grid worlds' states hold no clock).

    ``instruction_mlp=False`` (an option; the paper embeds the instruction like a state: 32 units
    per dimension, then ReLU 256 -> 64) feeds the per-dimension embeddings, concatenated, to the
    body. Its first layer is then a sum of one term per instruction dimension, so an unseen
    combination of familiar parts (MetaCook's held-out recipes: A seen first, B seen second, never
    together) gets a pre-activation made of trained terms, where the MLP maps it to an embedding
    no training recipe had (the probe in ``research/cook_composition_probe.py`` compares the two;
    measured runs are in docs/results/metacook.md).

    ``recurrent_size`` > 0 (an option, the authors' final code; the paper's network is
    feed-forward) runs an LSTM of that size over the execution episode's [e(s); e(i)] and feeds its
    output, concatenated with z, to the body: Q^exe(s_t, i, z, h_t) with h_t the episode so far.
    z is not an LSTM input, so one pass over an episode serves both of the update's z sources.
    The LSTM starts from zeros at each execution episode's first step.
    """

    TIME_EMBED_DIM = 16

    def __init__(
        self,
        observation_space: spaces.Dict,
        n_actions: int,
        z_dim: int = 64,
        hidden_sizes: Sequence[int] = (64,),
        time_steps: int = 0,
        instruction_mlp: bool = True,
        recurrent_size: int = 0,
        image_downsample: int = 1,
    ) -> None:
        super().__init__()
        hidden_sizes = check_layer_sizes("execution_hidden_sizes", hidden_sizes)
        self.state_embed = make_state_embedder(observation_space["obs"], image_downsample=image_downsample)
        instruction_nvec = observation_space["instruction"].nvec
        # the paper's MLP is the embedder's default; without it, the per-dimension tables alone
        if instruction_mlp:
            self.instruction_embed = MultiDiscreteEmbedder(instruction_nvec)
        else:
            self.instruction_embed = MultiDiscreteEmbedder(instruction_nvec, hidden_dims=())
        embed_dim = self.state_embed.embed_dim + self.instruction_embed.embed_dim
        self.time_steps = int(time_steps)
        self.time_embed: Optional[nn.Embedding] = None
        if self.time_steps > 0:
            self.time_embed = nn.Embedding(self.time_steps + 1, self.TIME_EMBED_DIM)
            embed_dim += self.TIME_EMBED_DIM
        self.recurrent_size = int(recurrent_size)
        self.lstm: Optional[nn.LSTM] = None
        if self.recurrent_size > 0:
            self.lstm = nn.LSTM(embed_dim, self.recurrent_size, batch_first=True)
            embed_dim = self.recurrent_size
        self.body, width = relu_mlp(embed_dim + z_dim, hidden_sizes)
        self.head = DuelingHead(width, n_actions)

    @property
    def recurrent(self) -> bool:
        return self.lstm is not None

    def embed(
        self,
        states: Union[th.Tensor, DistinctFrames],
        instructions: th.Tensor,
        steps: Optional[th.Tensor] = None,
    ) -> th.Tensor:
        """[e(s); e(i)] (and e(t) with ``time_steps``): computed once and shared by the rows that
        differ only in z. A recurrent network's LSTM runs over these (:meth:`recur`). Image
        ``states`` may come as their :class:`~sb3_dream.common.embedders.DistinctFrames`."""
        return self.join(self.state_embed(states), instructions, steps)

    def join(self, state_embedding: th.Tensor, instructions: th.Tensor, steps: Optional[th.Tensor] = None) -> th.Tensor:
        """:meth:`embed` from e(s) already computed."""
        parts = [state_embedding, self.instruction_embed(instructions)]
        if self.time_embed is not None:
            if steps is None:
                raise ValueError("this execution Q-network takes the execution step: pass steps")
            parts.append(self.time_embed(steps.long().clamp(0, self.time_steps)))
        return th.cat(parts, dim=-1)

    def recur(self, embeddings: th.Tensor, hidden: Optional[LSTMState] = None) -> Tuple[th.Tensor, LSTMState]:
        """The LSTM over ``embeddings`` [B, T, D] (one fused unroll) from ``hidden`` (default zeros):
        the outputs [B, T, recurrent_size] that :meth:`q_values` takes, and the final state."""
        if self.lstm is None:
            raise ValueError("this execution Q-network is feed-forward (recurrent_size=0)")
        return self.lstm(embeddings, hidden)

    def q_values(self, embedding: th.Tensor, z: th.Tensor) -> th.Tensor:
        """Q from :meth:`embed`'s output (feed-forward) or :meth:`recur`'s (recurrent) and z."""
        return self.head(self.body(th.cat([embedding, z], dim=-1)))

    def forward(
        self,
        states: th.Tensor,
        instructions: th.Tensor,
        z: th.Tensor,
        steps: Optional[th.Tensor] = None,
        hidden: Optional[LSTMState] = None,
        episode_start: Optional[th.Tensor] = None,
    ) -> Tuple[th.Tensor, Optional[LSTMState]]:
        """Q of one step of each of B episodes (acting): ``[B, A]``, and a recurrent network's new
        state. A recurrent network continues each episode from ``hidden`` (each ``[1, B, size]``),
        from zeros where ``episode_start`` ([B] bool) is set (default: every row starts)."""
        embedding = self.embed(states, instructions, steps)
        if self.lstm is not None:
            if hidden is not None and episode_start is not None:
                keep = (~episode_start)[None, :, None].to(embedding.dtype)
                hidden = (hidden[0] * keep, hidden[1] * keep)
            else:
                hidden = None
            out, hidden = self.recur(embedding[:, None], hidden)
            embedding = out[:, 0]
        return self.q_values(embedding, z), hidden

    def transition_inputs(self, batch: ExecutionBatch) -> Tuple[th.Tensor, th.Tensor]:
        """What the body takes with z for each transition's s (with gradient) and s' (without), ``[B, D]``
        each: what :meth:`forward` computed for them while acting, written once for the losses."""
        if self.lstm is not None:
            current, following = self._episode_inputs(batch)
            return current, following.detach()
        if batch.state_frames is not None and isinstance(self.state_embed, ImageEmbedder):
            # each distinct frame of s and s' through the CNN once; s' reuses the frames s holds
            e_current, e_following = self.state_embed.embed_pair(
                batch.state_frames, batch.next_state_frames, batch.shared_frames
            )
            current = self.join(e_current, batch.instructions, batch.steps)
            with th.no_grad():
                following = self.join(e_following, batch.instructions, next_steps(batch))
            return current, following
        current = self.embed(batch.states, batch.instructions, batch.steps)
        with th.no_grad():
            following = self.next_inputs(batch)
        return current, following

    def next_inputs(self, batch: ExecutionBatch) -> th.Tensor:
        """:meth:`transition_inputs`' s' part alone (a target network's pass)."""
        if self.lstm is not None:
            return self._episode_inputs(batch)[1]
        return self.embed(_frames_or(batch.next_state_frames, batch.next_states), batch.instructions, next_steps(batch))

    def _episode_inputs(self, batch: ExecutionBatch) -> Tuple[th.Tensor, th.Tensor]:
        """A recurrent network's LSTM outputs for each transition's s and s' ([B, D] each).

        The batch holds whole episodes (``execution_sampling="episodes"``: transition j is step
        ``steps[j]`` of episode ``trajectories[j]``), so each episode's states s_0 .. s_L (s_L: its
        last transition's s') are laid out as one [E, L+1] sequence, and one fused LSTM pass from
        zeros gives h_t for s_t and h_{t+1} for s', as acting step by step did.
        """
        episode, step = batch.trajectories, batch.steps
        n_episodes, horizon = int(episode.max()) + 1, int(step.max()) + 1
        length = th.zeros(n_episodes, dtype=step.dtype, device=step.device).scatter_reduce(
            0, episode, step + 1, reduce="amax"
        )
        last = step + 1 == length[episode]  # where s' is the episode's last state, no later s holds it
        embedding = self.embed(_frames_or(batch.state_frames, batch.states), batch.instructions, step)
        last_state = self.embed(batch.next_states[last], batch.instructions[last], step[last] + 1)
        sequence = embedding.new_zeros(n_episodes, horizon + 1, embedding.shape[1])
        sequence = sequence.index_put((episode, step), embedding)
        sequence = sequence.index_put((episode[last], step[last] + 1), last_state)
        out, _ = self.recur(sequence)
        return out[episode, step], out[episode, step + 1]


class ExplorationQNetwork(nn.Module):
    """Q^exp(s_t, tau_:t, .): [e(s_t); e(a_{t-1}); e(r_{t-1})] -> 64 + ReLU -> LSTM 64 -> dueling head.

    Previous actions are embedded with a 16-d table (index 0 = none), previous rewards with a
    16-d linear layer (always 0 in reward-free exploration). The LSTM starts from zeros at each
    trial; training unrolls it fused over whole sequences.

    ``time_steps`` > 0 (an option; not the paper's network) adds e(t), a 16-d embedding of the step
    t within the exploration episode (clipped to ``time_steps``), to the input. The exploration
    episode ends at a fixed horizon, so how much a step is worth depends on the steps left (a
    wasted step early can cost the last bus ride); the LSTM can only count them, while with t the
    horizon-terminal TD targets are Markov (Pardo et al., 2018, "Time Limits in RL").
    """

    TIME_EMBED_DIM = 16

    def __init__(
        self,
        observation_space: spaces.Dict,
        n_actions: int,
        hidden_size: int = 64,
        time_steps: int = 0,
        image_downsample: int = 1,
    ) -> None:
        super().__init__()
        self.state_embed = make_state_embedder(observation_space["obs"], image_downsample=image_downsample)
        self.prev_action_embed = nn.Embedding(n_actions + 1, 16)
        self.prev_reward_embed = nn.Linear(1, 16)
        in_dim = self.state_embed.embed_dim + 32
        self.time_steps = int(time_steps)
        self.time_embed: Optional[nn.Embedding] = None
        if self.time_steps > 0:
            self.time_embed = nn.Embedding(self.time_steps + 1, self.TIME_EMBED_DIM)
            in_dim += self.TIME_EMBED_DIM
        self.body = nn.Sequential(nn.Linear(in_dim, 64), nn.ReLU())
        self.lstm = nn.LSTM(64, hidden_size, batch_first=True)
        self.head = DuelingHead(hidden_size, n_actions)
        self.hidden_size = hidden_size

    def forward(
        self,
        states: Union[th.Tensor, DistinctFrames],
        prev_actions: th.Tensor,
        prev_rewards: th.Tensor,
        hidden: Optional[LSTMState] = None,
        steps: Optional[th.Tensor] = None,
    ) -> Tuple[th.Tensor, LSTMState]:
        """Inputs [B, T, ...] (``steps`` [B, T] with ``time_steps``; image states may come as their
        :class:`~sb3_dream.common.embedders.DistinctFrames`) -> Q-values [B, T, A] and the final
        LSTM state."""
        parts = [self.state_embed(states), self.prev_action_embed(prev_actions), self.prev_reward_embed(prev_rewards)]
        if self.time_embed is not None:
            if steps is None:
                raise ValueError("this exploration Q-network takes the exploration step: pass steps")
            parts.append(self.time_embed(steps.long().clamp(0, self.time_steps)))
        h, hidden = self.lstm(self.body(th.cat(parts, dim=-1)), hidden)
        return self.head(h), hidden


class DreamPolicy(BasePolicy):
    """DREAM's networks with their target copies (Algorithm 1, lines 2-5).

    Two optimizers: ``optimizer`` for the execution side (Q^exe, f, g: they share the execution
    losses) and ``exploration_optimizer`` for Q^exp (trained on rewards computed without gradient).

    Options (``policy_kwargs``): ``z_dim``, ``execution_hidden_sizes`` the layers of Q^exe's body
    (the paper's ``(64,)``), ``execution_time_input`` (default False, the paper's network): Q^exe
    also sees the step within the execution episode (see :class:`ExecutionQNetwork`), and
    ``exploration_time_input`` (default False): Q^exp also sees the step within the exploration
    episode (see :class:`ExplorationQNetwork`), ``execution_instruction_mlp`` (default True, the
    paper's network): False gives Q^exe the instruction's per-dimension embeddings without the MLP
    over them, for recipes never seen together (see :class:`ExecutionQNetwork`). ``horizon`` (the
    inner-episode horizon) is set by DREAM from the env. ``optimizer_kwargs``: Adam runs fused
    (``fused=True``) unless they set ``fused`` or ``foreach``.

    ``execution_recurrent`` (default False, the paper's feed-forward network): Q^exe runs an LSTM of
    64 over the execution episode, as in the authors' final code (see :class:`ExecutionQNetwork`);
    DREAM then learns from whole execution episodes (``execution_sampling="episodes"``).

    ``execution_weight_decay`` (default 0, the paper's plain Adam) > 0 decays Q^exe's weights, and
    only those, by ``lr * execution_weight_decay`` per step, apart from the gradient (AdamW's
    decoupled weight decay): a regulariser for the composition of unseen instructions from their
    parts, which the training split cannot otherwise reward (measured in docs/results/metacook.md).
    The encoder and the decoder are not decayed: the bottleneck already bounds f, and g regresses
    onto it.

    ``image_downsample`` (default 1, the paper's CNN on the full frame) > 1, for image observations
    (SignNav3D-v0): every network's CNN sees each frame average-pooled by that factor (2: 80 x 60 ->
    40 x 30; see :class:`~sb3_dream.common.embedders.ImageEmbedder`). The CNNs are almost all of an
    update's arithmetic on SignNav3D, so pooling them cuts an update's cost (docs/speed.md).

    ``decoder_hidden_size`` (default 128, the paper's decoder) is the size of the decoder's LSTM
    over the exploration trajectory. The decoder's forward and backward passes are the largest part
    of the execution update on the grid worlds, so a smaller LSTM (64) makes an update cheaper
    (docs/speed.md); the bottleneck's z keeps its ``z_dim``.
    """

    EXECUTION_LSTM_SIZE = 64  # the authors' LSTMCell over the execution episode

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        problem_nvec: Optional[np.ndarray] = None,
        z_dim: int = 64,
        execution_hidden_sizes: Sequence[int] = (64,),
        execution_time_input: bool = False,
        exploration_time_input: bool = False,
        execution_instruction_mlp: bool = True,
        execution_recurrent: bool = False,
        execution_weight_decay: float = 0.0,
        image_downsample: int = 1,
        decoder_hidden_size: int = 128,
        horizon: Optional[int] = None,
        optimizer_class: Type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: Optional[Dict[str, Any]] = None,
    ) -> None:
        super().__init__(
            observation_space, action_space, optimizer_class=optimizer_class, optimizer_kwargs=optimizer_kwargs
        )
        if problem_nvec is None:
            raise ValueError("problem_nvec is required (the sizes of the env's problem_features)")
        self.problem_nvec = np.asarray(problem_nvec, dtype=np.int64)
        self.z_dim = z_dim
        n_actions = int(action_space.n)
        self.image_downsample = check_positive_int("image_downsample", image_downsample)
        if self.image_downsample > 1 and not is_image_space(
            observation_space["obs"], check_channels=False, normalized_image=False
        ):
            raise ValueError(
                f"image_downsample={image_downsample} applies to image observations only; this env's obs space "
                f"is {observation_space['obs']}: leave it at 1"
            )
        self.encoder = ProblemEncoder(self.problem_nvec, z_dim)
        self.decoder_hidden_size = check_positive_int("decoder_hidden_size", decoder_hidden_size)
        self.decoder = TrajectoryDecoder(
            observation_space["obs"],
            n_actions,
            z_dim,
            hidden_size=self.decoder_hidden_size,
            image_downsample=self.image_downsample,
        )
        time_inputs = {"execution_time_input": execution_time_input, "exploration_time_input": exploration_time_input}
        flags = {
            **time_inputs,
            "execution_instruction_mlp": execution_instruction_mlp,
            "execution_recurrent": execution_recurrent,
        }
        for name, flag in flags.items():
            check_bool(name, flag)
        for name, flag in time_inputs.items():  # the clock's embedding has one row per step
            if flag and not (isinstance(horizon, (int, np.integer)) and horizon >= 1):
                raise ValueError(f"{name} needs the inner-episode horizon >= 1, got horizon={horizon!r}")
        self.execution_time_input, self.horizon = bool(execution_time_input), horizon
        self.exploration_time_input = bool(exploration_time_input)
        time_steps = int(horizon) if execution_time_input else 0
        self.execution_instruction_mlp = bool(execution_instruction_mlp)
        self.execution_recurrent = bool(execution_recurrent)
        self.execution_q = ExecutionQNetwork(
            observation_space,
            n_actions,
            z_dim,
            execution_hidden_sizes,
            time_steps,
            self.execution_instruction_mlp,
            recurrent_size=self.EXECUTION_LSTM_SIZE if self.execution_recurrent else 0,
            image_downsample=self.image_downsample,
        )
        self.execution_hidden_sizes = tuple(int(h) for h in execution_hidden_sizes)  # checked by the network
        time_steps = int(horizon) if exploration_time_input else 0
        self.exploration_q = ExplorationQNetwork(
            observation_space, n_actions, time_steps=time_steps, image_downsample=self.image_downsample
        )
        self.encoder_target = copy.deepcopy(self.encoder)
        self.decoder_target = copy.deepcopy(self.decoder)
        self.execution_q_target = copy.deepcopy(self.execution_q)
        self.exploration_q_target = copy.deepcopy(self.exploration_q)
        for target in self.targets():
            target.requires_grad_(False)
        self.sync_targets()

        self.optimizer_kwargs = default_optimizer_kwargs(optimizer_class, self.optimizer_kwargs)
        self.execution_weight_decay = check_non_negative("execution_weight_decay", execution_weight_decay)
        execution_params = [*self.encoder.parameters(), *self.decoder.parameters(), *self.execution_q.parameters()]
        if self.execution_weight_decay == 0:
            self.optimizer = self.optimizer_class(execution_params, lr=lr_schedule(1), **self.optimizer_kwargs)
        else:
            self.optimizer = self._decayed_execution_optimizer(lr_schedule(1))
        self.exploration_optimizer = self.optimizer_class(
            self.exploration_q.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs
        )

    def _decayed_execution_optimizer(self, lr: float) -> th.optim.Optimizer:
        """AdamW over two parameter groups: f and g without decay (Adam's step), Q^exe with it."""
        if self.optimizer_class is not th.optim.Adam or "weight_decay" in self.optimizer_kwargs:
            raise ValueError(
                "execution_weight_decay needs the default optimizer (optimizer_class Adam, no weight_decay in "
                f"optimizer_kwargs), got optimizer_class={self.optimizer_class.__name__} and "
                f"optimizer_kwargs={self.optimizer_kwargs}"
            )
        groups = [
            {"params": [*self.encoder.parameters(), *self.decoder.parameters()], "weight_decay": 0.0},
            {"params": list(self.execution_q.parameters()), "weight_decay": self.execution_weight_decay},
        ]
        return th.optim.AdamW(groups, lr=lr, **self.optimizer_kwargs)

    def onlines(self) -> Tuple[nn.Module, ...]:
        return self.encoder, self.decoder, self.execution_q, self.exploration_q

    def targets(self) -> Tuple[nn.Module, ...]:
        return self.encoder_target, self.decoder_target, self.execution_q_target, self.exploration_q_target

    def sync_targets(self, tau: float = 1.0) -> None:
        """Copy every online network into its target (Algorithm 1, lines 22-23); with ``tau`` < 1,
        move each target parameter that fraction of the way instead (SB3's Polyak update)."""
        for online, target in zip(self.onlines(), self.targets()):
            if tau == 1:
                target.load_state_dict(online.state_dict())
            else:
                polyak_update(online.parameters(), target.parameters(), tau)

    def _get_constructor_parameters(self) -> Dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            problem_nvec=self.problem_nvec,
            z_dim=self.z_dim,
            execution_hidden_sizes=self.execution_hidden_sizes,
            execution_time_input=self.execution_time_input,
            exploration_time_input=self.exploration_time_input,
            execution_instruction_mlp=self.execution_instruction_mlp,
            execution_recurrent=self.execution_recurrent,
            execution_weight_decay=self.execution_weight_decay,
            image_downsample=self.image_downsample,
            decoder_hidden_size=self.decoder_hidden_size,
            horizon=self.horizon,
            lr_schedule=self._dummy_schedule,
        )
        return data

    def _predict(self, observation: Any, deterministic: bool = True) -> th.Tensor:
        raise NotImplementedError("DREAM acts through DREAM.predict, which keeps the trial's state")

    def set_training_mode(self, mode: bool) -> None:
        onlines = self.onlines()
        if self.training == mode and all(net.training == mode for net in onlines):
            return  # called at every rollout, update and meta-test step: skip walking the module tree
        for net in onlines:
            net.train(mode)
        self.training = mode
