"""Forward and backward time of SignNav3D's CNN (:class:`~sb3_dream.common.embedders.ImageEmbedder`)
over one update's worth of frames, in three memory layouts.

    python benchmarks/image_embedder_speed.py [--frames 672] [--repeats 5]

672 frames are 32 exploration trajectories of 21 states: a DREAM update embeds that many about five
times (the decoder, its target, the exploration Q and its target, over two batches), three of them
without gradient. The env's observations are channel-last (60, 80, 3); the embedder permutes them,
so its convolutions already see a channels-last tensor. The variants: the weights as they are,
the weights also channels-last, and the frames copied to contiguous channel-first first. The
median over ``--repeats`` (the first dropped as warm-up) is printed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_dream.common.embedders import ImageEmbedder

VARIANTS = ("as is", "weights channels_last", "frames NCHW-contiguous")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=672)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    th.manual_seed(0)
    frames = th.randint(0, 255, (args.frames, 60, 80, 3), dtype=th.uint8)
    last = ImageEmbedder(spaces.Box(0, 255, (60, 80, 3), np.uint8))  # the env's layout
    first = ImageEmbedder(spaces.Box(0, 255, (3, 60, 80), np.uint8))
    first.load_state_dict(last.state_dict())
    times = {v: [] for v in VARIANTS}
    for _ in range(args.repeats + 1):
        for variant in VARIANTS:  # in turn, so that a busy machine slows each alike
            embedder, x = last, frames
            last.to(memory_format=th.channels_last if variant == "weights channels_last" else th.contiguous_format)
            if variant == "frames NCHW-contiguous":
                embedder, x = first, frames.permute(0, 3, 1, 2).contiguous()
            embedder.zero_grad()
            start = time.perf_counter()
            out = embedder(x)
            forward = time.perf_counter() - start
            out.sum().backward()
            times[variant].append((forward, time.perf_counter() - start))
    print(f"ImageEmbedder over {args.frames} frames (60x80 RGB), {args.threads} thread(s), median of {args.repeats}:")
    for variant in VARIANTS:
        t = np.median(np.array(times[variant][1:]), axis=0) * 1000
        print(f"  {variant:24s} forward {t[0]:6.0f} ms   forward + backward {t[1]:6.0f} ms")


if __name__ == "__main__":
    main()
