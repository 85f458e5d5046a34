"""DREAM's training throughput with the paper's hyperparameters, and where the time goes.

Both agents learn from the first trials (learning-start thresholds are set low so that every
measured step pays for its updates: one exploration and one execution update per 4 env steps,
batch 32, as in the paper). Prints env steps per second and the share of wall-clock spent acting
(the networks choosing actions), stepping the envs, and in gradient updates.

    python benchmarks/dream_speed.py --env MetaBus-v0 --steps 4000 --n-envs 1 8 [--threads 1]
    python benchmarks/dream_speed.py --parallel-updates off  # sequential (default: DREAM's "auto")
    python benchmarks/dream_speed.py --compile               # torch.compile the networks' forwards
    python benchmarks/dream_speed.py --execution-target-z encoder   # the authors' target z
    python benchmarks/dream_speed.py --loop-adam             # Adam's per-parameter loop (default: fused)
    python benchmarks/dream_speed.py --n-envs 1 --profile 60 # + torch.profiler over 60 updates
    python benchmarks/dream_speed.py --env SignNav3D-v0 --device cuda   # the networks on a GPU

Per-update times, for comparisons finer than the machine's drift (its speed can change by a third
within an hour): one model per variant, all in this process, timed in interleaved rounds, medians.

    python benchmarks/dream_speed.py --compare-updates 5 --threads 1 2   # sequential vs parallel
    python benchmarks/dream_speed.py --compare-updates 5 --variants parallel parallel+loop-adam
    python benchmarks/dream_speed.py --parts --variants default   # each part of the update, timed alone,
                                                                  # with its FLOPs and its GFLOP/s

Image envs: each network's CNN embeds each distinct frame of a batch once (the default);
``every-frame`` (a variant, or ``--every-frame``) embeds every position's frame, as before.
``--parts`` also counts the frames each CNN pass takes.

    python benchmarks/dream_speed.py --env SignNav3D-v0 --warmup 300 --compare-updates 5 --updates 5 \
        --variants default every-frame [--full-explorations]   # B_exp: walks of all 20 steps
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_dream import DREAM, PRESETS
from sb3_dream.common.embedders import ImageEmbedder
from sb3_dream.dream import updates
from timing import interleaved_rounds, summary


def timed(obj, name: str, totals: dict, key: str, device: th.device) -> None:
    original = getattr(obj, name)
    # CUDA kernels run asynchronously: wait for them, or their time lands on whichever part syncs next
    sync = th.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            sync()
            totals[key] += time.perf_counter() - start

    setattr(obj, name, wrapper)


NETWORKS = ("encoder", "decoder", "execution_q", "exploration_q")


def measure(
    env_id: str,
    env_kwargs: dict,
    n_envs: int,
    steps: int,
    warmup: int,
    seed: int,
    compile_networks: bool = False,
    profile_updates: int = 0,
    every_frame: bool = False,
    **kwargs,
) -> dict:
    env = make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs)
    model = DREAM(env, seed=seed, exploration_learning_starts=10, execution_learning_starts=10, **kwargs)
    set_distinct_frames(model, not every_frame)
    if compile_networks:  # every network and its target; trajectory lengths vary, hence dynamic shapes
        for name in NETWORKS + tuple(f"{n}_target" for n in NETWORKS):
            network = getattr(model.policy, name)
            network.forward = th.compile(network.forward, dynamic=True)
    model.learn(warmup)  # fill the buffers (and compile) so that both agents update from here on
    totals: dict = defaultdict(float)
    timed(model.env, "step", totals, "env", model.device)
    timed(model, "_sample_action", totals, "act", model.device)  # the networks choosing actions
    timed(model, "train", totals, "update", model.device)
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    wall = time.perf_counter() - start
    result = {"sps": steps / wall, "wall": wall, **{k: v / wall for k, v in totals.items()}}
    if profile_updates:
        result["profile"] = profile(model, profile_updates)
    env.close()
    return result


def profile(model: DREAM, n_updates: int) -> str:
    """torch.profiler's operator table over ``n_updates`` updates (one of each part, batch 32)."""
    activities = [th.profiler.ProfilerActivity.CPU]
    on_gpu = model.device.type == "cuda"
    if on_gpu:  # the kernels' own time too: a GPU waiting for kernel launches shows far less than the host
        activities.append(th.profiler.ProfilerActivity.CUDA)
    with th.profiler.profile(activities=activities) as prof:
        model.train(n_updates, model.batch_size)
        if on_gpu:
            th.cuda.synchronize()
    ops = prof.key_averages()
    total = sum(op.self_cpu_time_total for op in ops)
    lstm = sum(op.self_cpu_time_total for op in ops if "rnn" in op.key or "lstm" in op.key)
    table = ops.table(sort_by="self_cpu_time_total", row_limit=15)
    summary = f"{total / n_updates / 1e3:.1f} ms of host time per update, {lstm / total:.0%} of it in LSTM kernels"
    if on_gpu:
        summary += f" (launched; the table's Self CUDA time total is the GPU's own, over {n_updates} updates)"
    return f"{table}\n{summary}"


PARALLEL_UPDATES = {"auto": "auto", "on": True, "off": False}  # --parallel-updates -> DREAM(parallel_updates=...)

# The variants --compare-updates can time: DREAM kwargs on top of the paper's hyperparameters.
VARIANTS = {
    "default": {},  # parallel_updates="auto"
    "sequential": {"parallel_updates": False},
    "parallel": {"parallel_updates": True},
    "fused-adam": {"policy_kwargs": {"optimizer_kwargs": {"fused": True}}},  # DREAM's default
    "loop-adam": {"policy_kwargs": {"optimizer_kwargs": {"fused": False}}},  # torch's per-parameter loop
    "encoder-target": {"execution_target_z": "encoder"},
    "episodes": {"execution_sampling": "episodes"},  # whole execution episodes per update
    # the authors' final execution Q, an LSTM over each execution episode (needs whole episodes)
    "recurrent-execution": {"execution_sampling": "episodes", "policy_kwargs": {"execution_recurrent": True}},
    # PRESETS["laptop"]'s networks and sampling (its schedules are the benchmark's own)
    "laptop": {k: v for k, v in PRESETS["laptop"].items() if k in ("policy_kwargs", "execution_sampling")},
    "decoder64": {"policy_kwargs": {"decoder_hidden_size": 64}},  # the decoder's LSTM of 64, not 128
    "exec2": {"execution_update_ratio": 2},  # two execution updates per exploration update
    "alternate": {"execution_z": "alternate"},  # one execution loss per update, its z source in turn
    # image envs (SignNav3D-v0): every CNN sees the frames average-pooled 2x2
    "downsample2": {"policy_kwargs": {"image_downsample": 2}},
    # image envs: every position's frame through the CNNs (before distinct frames; not a DREAM kwarg)
    "every-frame": {},
}
BUFFER_VARIANTS = {"every-frame": {"distinct_frames": False}}  # set on the replay buffers after construction


def set_distinct_frames(model: DREAM, on: bool) -> None:
    """Whether the sampled batches carry each distinct image frame once (DREAM's default) or not."""
    model.replay_buffer.exploration.distinct_frames = on
    model.replay_buffer.execution.distinct_frames = on


def make_variant(name: str, env, seed: int) -> DREAM:
    """A DREAM model of a variant (or several joined by "+"), learning from the first trials."""
    model = DREAM(env, seed=seed, exploration_learning_starts=10, execution_learning_starts=10, **variant_kwargs(name))
    for part in name.split("+"):
        if BUFFER_VARIANTS.get(part, {}).get("distinct_frames") is False:
            set_distinct_frames(model, False)
    return model


def variant_kwargs(name: str) -> dict:
    """DREAM kwargs of a variant, or of several joined by "+" (e.g. "parallel+fused-adam")."""
    kwargs: dict = {}
    for part in name.split("+"):
        if part not in VARIANTS:
            raise SystemExit(f"unknown variant {part!r}; accepted: {', '.join(VARIANTS)}, joined by '+'")
        for key, value in VARIANTS[part].items():
            kwargs[key] = {**kwargs.get(key, {}), **value} if isinstance(value, dict) else value
    return kwargs


def fill_full_explorations(model: DREAM, env_id: str, env_kwargs: dict, seed: int) -> None:
    """Replace every exploration trajectory in B_exp by a random walk of the full horizon that never
    takes the end-episode action: the batches of a run whose explorations take every step (the
    warm-up's random explorations end after a few steps, so its batches are mostly padding).
    The execution transitions keep pointing at their slots, so their trajectories are such walks too."""
    import gymnasium as gym

    from sb3_dream.dream.acting import model_states

    trial_env = gym.make(env_id, **env_kwargs).unwrapped
    trial_env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    buffer, space = model.replay_buffer.exploration, model.observation_space["obs"]
    moves = [a for a in range(trial_env.n_actions) if a != trial_env.end_episode_action]
    for slot in range(len(buffer)):
        trial_env._set_problem(int(rng.integers(trial_env.n_problems)))
        actions = rng.choice(moves, size=buffer.max_length)
        frames = [trial_env._inner_reset()] + [trial_env._inner_step(int(a))[0] for a in actions]
        buffer.states[slot] = model_states(np.stack(frames), space)
        buffer.actions[slot], buffer.lengths[slot] = actions, buffer.max_length
        buffer.prev_actions[slot] = np.concatenate([[0], actions + 1])  # 0: none, a + 1: action a
    trial_env.close()


def compare_updates(
    env_id: str,
    env_kwargs: dict,
    variants: list,
    threads: list,
    rounds: int,
    n_updates: int,
    warmup: int,
    seed: int,
    full_explorations: bool = False,
) -> None:
    """Milliseconds per update (one exploration and one execution update, batch 32) of each variant
    at each torch thread count: ``rounds`` interleaved rounds of ``n_updates`` updates per model."""
    models = {}
    for name in variants:
        env = make_vec_env(env_id, n_envs=1, seed=seed, env_kwargs=env_kwargs)
        model = make_variant(name, env, seed)
        model.learn(warmup)  # both agents update from here on
        if full_explorations:
            fill_full_explorations(model, env_id, env_kwargs, seed)
        models[name] = model
    keys = [(name, n_threads) for n_threads in threads for name in models]
    entries = [
        (
            f"{name}@{n_threads}",
            lambda m=models[name]: m.train(n_updates, m.batch_size),
            lambda n=n_threads: th.set_num_threads(n),
        )
        for name, n_threads in keys
    ]
    times = interleaved_rounds(entries, rounds, units=n_updates)
    print(f"ms per update on {env_id}, median of {rounds} interleaved rounds of {n_updates} updates (min - max)")
    width = max(len(name) for name in variants) + 2
    print(f"{'variant':>{width}}{'threads':>9}{'median':>9}{'range':>16}")
    for name, n_threads in keys:
        median, low, high = summary(times[f"{name}@{n_threads}"])
        print(f"{name:>{width}}{n_threads:>9}{median:>9.1f}{f'{low:.1f} - {high:.1f}':>16}")


def _lstm_flops(input_shape, w_ih_shape, w_hh_shape) -> int:
    """Multiply-adds x 2 of one LSTM layer's forward: every step's gates, W_ih x + W_hh h, for every row."""
    return 2 * input_shape[0] * input_shape[1] * w_ih_shape[0] * (w_ih_shape[1] + w_hh_shape[1])


# torch's FLOP counter knows matrix products but not the CPU's fused (oneDNN) LSTM kernels: their
# forward is counted like the products it does; the backward does twice that (gradients of the
# inputs and of the weights).
LSTM_FLOP_FORMULAS = {
    th.ops.aten.mkldnn_rnn_layer: lambda x, w_ih, w_hh, *args, out_shape=None, **kwargs: _lstm_flops(x, w_ih, w_hh),
    th.ops.aten.mkldnn_rnn_layer_backward: (
        lambda x, w_ih, w_hh, *args, out_shape=None, **kwargs: 2 * _lstm_flops(x, w_ih, w_hh)
    ),
}


def matmul_gflops(size: int = 512, repeats: int = 50) -> float:
    """This core's rate on a plain square matrix product: the yardstick for the update's parts."""
    a, b = th.randn(size, size), th.randn(size, size)
    for _ in range(5):
        a @ b
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    return 2 * size**3 * repeats / (time.perf_counter() - start) / 1e9


def update_parts(env_id: str, env_kwargs: dict, variant: str, n_updates: int, warmup: int, seed: int) -> None:
    """Milliseconds of each part of an update, run one after the other in this thread: what
    ``parallel_updates`` splits between the two threads (medians over ``n_updates`` updates), with
    each part's floating-point work (torch's FLOP counter, LSTM kernels included) and its rate."""
    from torch.utils.flop_counter import FlopCounterMode

    env = make_vec_env(env_id, n_envs=1, seed=seed, env_kwargs=env_kwargs)
    model = make_variant(variant, env, seed)
    model.parallel_updates = False  # the parts one after the other, in this thread
    model.learn(warmup)
    frames = count_cnn_frames(model)  # image envs: the frames each CNN pass takes
    model.policy.set_training_mode(True)
    buffers = model.replay_buffer
    times: dict = defaultdict(list)
    flops: dict = defaultdict(list)

    def timed_part(name: str, fn):
        start = time.perf_counter()
        result = fn()
        times[name].append((time.perf_counter() - start) * 1e3)
        return result

    def counted_part(name: str, fn):  # the same part again, untimed, for its FLOPs
        with FlopCounterMode(display=False, custom_mapping=LSTM_FLOP_FORMULAS) as counter:
            result = fn()
        flops[name].append(counter.get_total_flops())
        return result

    for i in range(n_updates):  # the order of DREAM._update with parallel_updates
        explored = buffers.sample_trajectories(model.batch_size, model._rng)
        exe, traj = buffers.sample_execution(
            model.batch_size, model._rng, episodes=model.execution_sampling == "episodes"
        )
        # Every 10th update is counted instead of timed (the counter slows what it counts); each
        # part runs once either way, so the networks follow the same updates.
        part = counted_part if i % 10 == 9 else timed_part
        target_q = part("worker: execution targets", lambda: updates.execution_target_q(model, exe, traj))
        codes = part("worker: reward pass (f, g)", lambda: updates.reward_codes(model.policy, explored))
        part("worker: exploration update", lambda: updates.exploration_update(model, explored, *codes))
        part("main: execution losses + step", lambda: updates.execution_update(model, exe, traj, lambda: target_q))
    print(f"ms per part on {env_id} ({variant}), median of {n_updates} updates, one thread")
    print(f"{'':>32}{'ms':>8}{'GFLOP':>8}{'GFLOP/s':>9}")
    ms = {k: statistics.median(v) for k, v in times.items()}
    gflop = {k: statistics.mean(v) / 1e9 for k, v in flops.items()}
    for name in ms:
        print(f"{name:>32}{ms[name]:>8.2f}{gflop[name]:>8.3f}{gflop[name] / ms[name] * 1e3:>9.1f}")
    for side in ("worker", "main"):
        side_ms = sum(v for k, v in ms.items() if k.startswith(side))
        side_gflop = sum(v for k, v in gflop.items() if k.startswith(side))
        label = f"{side} thread, in all"
        print(f"{label:>32}{side_ms:>8.2f}{side_gflop:>8.3f}{side_gflop / side_ms * 1e3:>9.1f}")
    print(f"a 512 x 512 matrix product on this core: {matmul_gflops():.1f} GFLOP/s")
    if frames:
        print(f"CNN passes per update (network, with gradient?): frames per pass, mean of {n_updates} updates")
        for (name, grad), rows in frames.items():
            print(f"{name:>22} {'grad' if grad else 'no grad':>8}: {sum(rows) / n_updates:7.1f}")
        print(f"{'in all':>31}: {sum(sum(rows) for rows in frames.values()) / n_updates:7.1f}")


def count_cnn_frames(model: DREAM) -> dict:
    """Hooks that record, for each network with a CNN, the frames of each pass, by gradient mode."""
    frames: dict = defaultdict(list)
    for name in NETWORKS + tuple(f"{n}_target" for n in NETWORKS):
        embed = getattr(getattr(model.policy, name), "state_embed", None)
        if isinstance(embed, ImageEmbedder):
            embed.cnn.register_forward_hook(
                lambda module, inputs, output, name=name: frames[name, th.is_grad_enabled()].append(len(inputs[0]))
            )
    return frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--variant", default=None, help="MetaBus variant (distracting, map, vanilla)")
    parser.add_argument("--steps", type=int, default=4000, help="measured env steps per setting")
    parser.add_argument("--warmup", type=int, default=1000)
    parser.add_argument("--n-envs", type=int, nargs="+", default=[1, 8])
    parser.add_argument(
        "--threads", type=int, nargs="+", default=[1], help="torch intra-op threads (several: --compare-updates)"
    )
    parser.add_argument("--train-freq", type=int, default=4, help="env steps per update (paper: 4)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--parallel-updates",
        nargs="?",
        const="on",
        default="auto",
        choices=list(PARALLEL_UPDATES),
        help="DREAM(parallel_updates=...): the exploration update and the passes without gradient in a second"
        " thread; 'auto' (DREAM's default: on with more than one core), bare flag: 'on', 'off': sequential",
    )
    parser.add_argument("--compile", action="store_true", help="torch.compile the networks' forward passes")
    parser.add_argument("--execution-target-z", default="own", choices=["own", "encoder"], help="DREAM's option")
    adam = parser.add_mutually_exclusive_group()
    adam.add_argument("--fused-adam", action="store_true", help="optimizer_kwargs fused=True (DREAM's default)")
    adam.add_argument("--loop-adam", action="store_true", help="optimizer_kwargs fused=False: the per-parameter loop")
    parser.add_argument("--device", default="cpu", help="torch device of the networks (cpu, cuda, auto)")
    parser.add_argument(
        "--image-downsample", type=int, default=1, help="policy_kwargs image_downsample (image envs; paper: 1)"
    )
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="then profile N updates")
    parser.add_argument(
        "--every-frame",
        action="store_true",
        help="image envs: embed every position's frame (not each distinct one once)",
    )
    parser.add_argument(
        "--compare-updates", type=int, default=0, metavar="ROUNDS", help="time updates of --variants instead"
    )
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["sequential", "parallel"],
        help=f"for --compare-updates: {', '.join(VARIANTS)}, or several joined by '+' (parallel+fused-adam)",
    )
    parser.add_argument("--updates", type=int, default=100, help="updates per round of --compare-updates")
    parser.add_argument(
        "--full-explorations",
        action="store_true",
        help="for --compare-updates: after the warm-up, B_exp holds random walks of the full exploration horizon",
    )
    parser.add_argument(
        "--parts", action="store_true", help="time each part of --updates updates (first of --variants), one thread"
    )
    args = parser.parse_args()
    env_kwargs = {"variant": args.variant} if args.variant else {}
    if args.parts:
        if args.updates < 10:  # every 10th update is the one whose FLOPs are counted
            parser.error(f"--parts needs --updates >= 10, got {args.updates}")
        th.set_num_threads(args.threads[0])
        update_parts(args.env, env_kwargs, args.variants[0], args.updates, args.warmup, args.seed)
        return
    if args.compare_updates:
        compare_updates(
            args.env, env_kwargs, args.variants, args.threads, args.compare_updates, args.updates, args.warmup,
            args.seed, full_explorations=args.full_explorations,
        )  # fmt: skip
        return
    if len(args.threads) > 1:
        parser.error("several --threads values need --compare-updates")
    th.set_num_threads(args.threads[0])
    parallel_updates = PARALLEL_UPDATES[args.parallel_updates]
    print(
        f"DREAM on {args.env} {env_kwargs or ''} train_freq={args.train_freq} torch threads={args.threads[0]}"
        f" parallel_updates={parallel_updates!r} compile={args.compile}"
        f" execution_target_z={args.execution_target_z} fused Adam={not args.loop_adam} device={args.device}"
        f" image_downsample={args.image_downsample} distinct frames={not args.every_frame}"
    )
    policy_kwargs = {"optimizer_kwargs": {"fused": not args.loop_adam}, "image_downsample": args.image_downsample}
    print(f"{'n_envs':>6}{'env steps/s':>13}{'acting':>9}{'env step':>10}{'updates':>9}{'other':>8}")
    for n in args.n_envs:
        r = measure(
            args.env, env_kwargs, n, args.steps, args.warmup, args.seed,
            compile_networks=args.compile, train_freq=args.train_freq, parallel_updates=parallel_updates,
            execution_target_z=args.execution_target_z, profile_updates=args.profile, policy_kwargs=policy_kwargs,
            device=args.device, every_frame=args.every_frame,
        )  # fmt: skip
        other = 1 - r["act"] - r["env"] - r["update"]
        print(f"{n:>6}{r['sps']:>13.0f}{r['act']:>9.0%}{r['env']:>10.0%}{r['update']:>9.0%}{other:>8.0%}")
        if "profile" in r:
            print(r["profile"])


if __name__ == "__main__":
    main()
