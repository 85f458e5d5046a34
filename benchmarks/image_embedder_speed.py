"""Forward and backward time of SignNav3D's CNN (:class:`~sb3_dream.common.embedders.ImageEmbedder`)
over one update's worth of frames, in the layouts it meets.

    python benchmarks/image_embedder_speed.py [--frames 672] [--repeats 5] [--downsample 1]

672 frames are 32 exploration trajectories of 21 states: a DREAM update embeds that many about five
times (the decoder, its target, the exploration Q and its target, over two batches), three of them
without gradient. DREAM's replay buffers hold the frames channel-first (SB3's ``VecTransposeImage``
turns the env's (60, 80, 3) into (3, 60, 80)); the env itself gives them channel-last. The
embedder runs its convolutions on a channels-last copy either way. The variants: channel-first
frames (what DREAM trains on), channel-last frames, and, for comparison, the same convolutions on
the contiguous channel-first tensor, as the embedder ran them before. ``--downsample 2`` times the
``image_downsample=2`` option instead. The median over ``--repeats`` (the first dropped as warm-up)
is printed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_dream.common.embedders import ImageEmbedder

VARIANTS = ("channel-first frames", "channel-last frames", "NCHW convolutions")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=672)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--downsample", type=int, default=1, help="ImageEmbedder(downsample=...)")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    th.manual_seed(0)
    frames_last = th.randint(0, 255, (args.frames, 60, 80, 3), dtype=th.uint8)
    frames_first = frames_last.permute(0, 3, 1, 2).contiguous()
    first = ImageEmbedder(spaces.Box(0, 255, (3, 60, 80), np.uint8), downsample=args.downsample)
    last = ImageEmbedder(spaces.Box(0, 255, (60, 80, 3), np.uint8), downsample=args.downsample)
    last.load_state_dict(first.state_dict())

    def nchw(x: th.Tensor) -> th.Tensor:  # the embedder's arithmetic, without the channels-last copy
        return first.linear(first.cnn(first.pool(x.float() / 255.0)))

    runs = {VARIANTS[0]: (first, frames_first), VARIANTS[1]: (last, frames_last), VARIANTS[2]: (nchw, frames_first)}
    times = {v: [] for v in VARIANTS}
    for _ in range(args.repeats + 1):
        for variant in VARIANTS:  # in turn, so that a busy machine slows each alike
            embed, x = runs[variant]
            first.zero_grad()
            last.zero_grad()
            start = time.perf_counter()
            out = embed(x)
            forward = time.perf_counter() - start
            out.sum().backward()
            times[variant].append((forward, time.perf_counter() - start))
    print(
        f"ImageEmbedder over {args.frames} frames (60x80 RGB, downsample {args.downsample}), "
        f"{args.threads} thread(s), median of {args.repeats}:"
    )
    for variant in VARIANTS:
        t = np.median(np.array(times[variant][1:]), axis=0) * 1000
        print(f"  {variant:22s} forward {t[0]:6.0f} ms   forward + backward {t[1]:6.0f} ms")


if __name__ == "__main__":
    main()
