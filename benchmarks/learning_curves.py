"""Learning curves of DREAM, DREAM (no bottleneck) and RL² on one trial env (the paper's Figure 5).

A thin front end of the experiment runner :mod:`sb3_dream.experiments` (which holds the code):
``--env`` and ``--variant`` become its ``--envs ENV[:variant=VARIANT]``; every other flag is the
runner's (``--algos``, ``--seeds``, ``--steps``, ``--preset``, ``--eval-freq``, ``--eval-trials``,
``--jobs``, ``--out``, ``--force``, ...; see ``python -m sb3_dream.experiments --help``). Runs are
always resumable: a finished run is skipped. The figure is drawn unless ``--no-plot``.

    python benchmarks/learning_curves.py --env MetaBus-v0 --variant map --algos dream rl2dqn \\
        --seeds 0 1 2 --steps 100000 --preset fast --out results/metabus_map
"""

from __future__ import annotations

import argparse
from typing import List, Optional, Sequence

from sb3_dream import experiments


def runner_args(argv: Optional[Sequence[str]] = None) -> List[str]:
    """This script's command line as the runner's."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--variant", default=None, help="MetaBus-v0's variant: distracting, map or vanilla")
    parser.add_argument("--resume", action="store_true", help="accepted for old scripts: runs always resume")
    parser.add_argument("--plot", action="store_true", help="accepted for old scripts: the figure is drawn by default")
    args, rest = parser.parse_known_args(argv)
    env = args.env + (f":variant={args.variant}" if args.variant else "")
    return ["--envs", env, *rest]


if __name__ == "__main__":
    experiments.main(runner_args())
