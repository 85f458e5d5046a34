"""One gradient step of each of DREAM's parts (Algorithm 1, lines 14-21): the networks' passes over
a sampled batch, the losses of :mod:`sb3_dream.dream.losses`, and the optimizer steps.

* :func:`execution_update`: the execution DDQN with z from the decoder and from the encoder (or
  from one of them, ``execution_z="alternate"``), the bottleneck and the decoder regression, all
  on the same execution samples, one optimizer step;
* :func:`exploration_update`: the exploration DDQN over whole trajectories on the
  information-gain rewards, recomputed from the current f and g (:func:`reward_codes`);
* :func:`parallel_update`: both, the exploration step in a second thread (same results).

With image states the sampled batches carry each distinct frame once
(:class:`~sb3_dream.common.embedders.DistinctFrames`), and every network's pass embeds those
instead of every position: a frame held by several positions (a blocked move, a revisited view, a
trajectory or frame sampled twice, the s' of one transition that is the s of another) goes through
each CNN once, and the padding after a trajectory's end, which no loss reads, not at all.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Callable, Dict, Optional, Sequence, Tuple, Union

import torch as th

from sb3_dream.common.embedders import DistinctFrames
from sb3_dream.dream import losses
from sb3_dream.dream.buffers import ExecutionBatch, TrajectoryBatch
from sb3_dream.dream.policies import DreamPolicy

if TYPE_CHECKING:
    from sb3_dream.dream.dream import DREAM

# Where the execution Q's z comes from: the decoder's g(tau^exp) or the encoder's F(z | T).
Z_SOURCES = ("decoder", "encoder")
# The statistic of each source's TD loss.
_LOSS_KEYS = {"decoder": "execution_loss_traj", "encoder": "execution_loss_prob"}


def trajectory_states(traj: TrajectoryBatch) -> Union[th.Tensor, DistinctFrames]:
    """What the networks embed of ``traj``'s states: its distinct frames where it has them."""
    return traj.states if traj.frames is None else traj.frames


@th.no_grad()
def reward_codes(policy: DreamPolicy, traj: TrajectoryBatch) -> Tuple[th.Tensor, th.Tensor]:
    """g of every prefix and f(T) for the exploration rewards: the current networks, as targets."""
    return policy.decoder(trajectory_states(traj), traj.actions), policy.encoder(traj.problem_features)


@th.no_grad()
def target_decoder_z(policy: DreamPolicy, traj: TrajectoryBatch) -> th.Tensor:
    """The target decoder's g(tau^exp) of each trajectory (the "own" target z of the loss with z = g)."""
    return policy.decoder_target(trajectory_states(traj), traj.actions, traj.lengths)


@th.no_grad()
def execution_target_q(
    model: "DREAM", exe: ExecutionBatch, traj: TrajectoryBatch, sources: Sequence[str] = Z_SOURCES
) -> th.Tensor:
    """The target Q^exe's values at each transition's s' [kB, A], one copy of the batch per z
    source of the execution loss (``sources``, :data:`Z_SOURCES`' names): for the loss with z = g
    the target z of ``execution_target_z``, for the loss with z from F the target encoder's F(mu).
    Target networks only, so another thread can compute it while the execution update runs its
    forward pass."""
    policy, owner = model.policy, exe.trajectories
    z_f_target = policy.encoder_target(traj.problem_features)[owner]
    z_targets = []
    for source in sources:
        if source == "decoder" and model.execution_target_z == "own":
            z_targets.append(target_decoder_z(policy, traj)[owner])
        else:  # the encoder's loss, or "encoder" targets for both (the authors' code, no decoder pass)
            z_targets.append(z_f_target)
    target_net = policy.execution_q_target
    return target_net.q_values(target_net.next_inputs(exe).repeat(len(sources), 1), th.cat(z_targets))


def execution_update(
    model: "DREAM",
    exe: ExecutionBatch,
    traj: TrajectoryBatch,
    target_q: Optional[Callable[[], th.Tensor]] = None,
    before_step: Optional[Callable[[], Any]] = None,
    sources: Sequence[str] = Z_SOURCES,
) -> Dict[str, float]:
    """One step on the execution DDQN with z from g and from F, the bottleneck and the decoder loss
    (Equations 2-4), all on the same execution samples (Appendix A).

    One decoder pass gives g of every prefix of the batch's trajectories ``traj``; transition j
    reads trajectory ``exe.trajectories[j]``. ``sources``: the z sources of the DDQN losses
    (:data:`Z_SOURCES`, both by default, Algorithm 1's lines 18-19; one with
    ``execution_z="alternate"``). ``target_q`` gives :func:`execution_target_q` (for the same
    ``sources``) when another thread computes it; ``before_step`` is called before the optimizer
    changes the networks.
    """
    policy, net = model.policy, model.policy.execution_q
    g_all = policy.decoder(trajectory_states(traj), traj.actions)  # [N, T+1, z]: every prefix in one pass
    f = policy.encoder(traj.problem_features)  # [N, z]
    owner = exe.trajectories
    z_g = g_all[th.arange(len(g_all), device=g_all.device), traj.lengths][owner]  # g(tau^exp) of each trial
    # Every source's DDQN loss in one forward: copy c of the batch's rows uses z from sources[c].
    z = th.cat([z_g if source == "decoder" else model.sample_encoder_z(f[owner]) for source in sources])
    copies = len(sources)
    inputs, next_inputs = net.transition_inputs(exe)
    q = net.q_values(inputs.repeat(copies, 1), z).gather(1, exe.actions.repeat(copies)[:, None]).squeeze(1)
    with th.no_grad():
        next_online = net.q_values(next_inputs.repeat(copies, 1), z)
    next_target = target_q() if target_q is not None else execution_target_q(model, exe, traj, sources)
    td_losses = losses.execution_td_losses(
        q,
        next_online,
        next_target,
        exe.rewards.repeat(copies),
        exe.dones.repeat(copies),
        model.gamma,
        len(exe.actions),
        n_step=model.execution_n_step,
        episodes=exe.trajectories,  # with execution_sampling="episodes", each transition's episode
        steps=exe.steps,
        windows=None if exe.window_rewards is None else (exe.window_rewards, exe.window_dones, exe.window_mask),
    )
    bottleneck = losses.bottleneck_loss(f, model.bottleneck_threshold) if model.bottleneck else f.new_zeros(())
    decoder_loss = losses.decoder_loss(g_all, f, traj.lengths)

    loss = sum(td_losses) + model.bottleneck_weight * bottleneck + decoder_loss
    policy.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    params = [p for group in policy.optimizer.param_groups for p in group["params"]]
    th.nn.utils.clip_grad_norm_(params, model.max_grad_norm)
    if before_step is not None:
        before_step()
    policy.optimizer.step()
    return {
        **{_LOSS_KEYS[source]: td.item() for source, td in zip(sources, td_losses)},
        "execution_q_mean": q.mean().item(),
        "decoder_loss": decoder_loss.item(),
        "f_norm_sq": f.pow(2).sum(dim=1).mean().item(),
        "bottleneck_loss": float(bottleneck.item()),
    }


def exploration_update(model: "DREAM", traj: TrajectoryBatch, g: th.Tensor, f: th.Tensor) -> Dict[str, float]:
    """One step on the exploration DDQN over whole trajectories (fused LSTM unroll), with the
    rewards of Equation 5 from the current f and g (``g``, ``f`` from :func:`reward_codes`)."""
    policy = model.policy
    rewards = losses.exploration_rewards(g, f, traj.lengths, model.reward_penalty)  # [B, T]
    clock = None  # the step of each state within its exploration episode, with exploration_time_input
    if policy.exploration_time_input:
        clock = th.arange(traj.actions.shape[1] + 1, device=rewards.device).expand(len(traj.actions), -1)
    inputs = (trajectory_states(traj), traj.prev_actions, traj.prev_rewards, None, clock)
    q_all, _ = policy.exploration_q(*inputs)  # [B, T+1, A]
    with th.no_grad():
        q_target_all, _ = policy.exploration_q_target(*inputs)
    loss, q, valid = losses.exploration_td_loss(
        q_all, q_target_all, traj.actions, rewards, traj.lengths, model.gamma, n_step=model.exploration_n_step
    )
    policy.exploration_optimizer.zero_grad(set_to_none=True)
    loss.backward()
    th.nn.utils.clip_grad_norm_(policy.exploration_q.parameters(), model.max_grad_norm)
    policy.exploration_optimizer.step()
    return {
        "exploration_loss": loss.item(),
        "exploration_q_mean": ((q * valid).sum() / valid.sum()).item(),
        "exploration_reward": ((rewards * valid).sum() / valid.sum()).item(),
    }


def parallel_update(
    model: "DREAM",
    explored: TrajectoryBatch,
    exe: ExecutionBatch,
    traj: TrajectoryBatch,
    sources: Sequence[str] = Z_SOURCES,
) -> Dict[str, float]:
    """``parallel_updates``: the no-gradient passes and the exploration update run in a second
    thread beside the execution update, with the same inputs, so with the same results.

    The worker runs, in order, the target networks' pass for the execution targets
    (:func:`execution_target_q`: the target decoder's z with ``execution_target_z="own"``, then the
    target Q^exe at s'), the reward pass of the current f and g over the exploration batch, and the
    exploration DDQN step. The execution update waits for the first before its TD errors, and for
    the second before its optimizer step changes f and g (their networks and optimizers are
    otherwise disjoint).
    """
    if model._update_thread is None:
        model._update_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dream-exploration")
    worker, policy = model._update_thread, model.policy
    target_q = worker.submit(execution_target_q, model, exe, traj, sources)
    codes = worker.submit(reward_codes, policy, explored)
    exploration = worker.submit(lambda: exploration_update(model, explored, *codes.result()))
    stats = execution_update(model, exe, traj, target_q=target_q.result, before_step=codes.result, sources=sources)
    return {**exploration.result(), **stats}
