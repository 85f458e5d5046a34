"""What a DREAM checkpoint's execution replay holds: transitions, episodes and rewards per (problem,
instruction) pair.

    python examples/replay_rewards.py results/run/SignNav3D-v0/checkpoints/dream_seed0.320000.pkl
    python examples/replay_rewards.py saved_buffer.pkl --env SignNav3D-v0

The buffer is the ``.pkl`` that ``model.save_replay_buffer`` writes (the experiment runner keeps one
with each checkpoint). The execution Q-network learns only from the rewards its replay holds, so a
pair with no positive reward there is one it cannot have learned to solve: in a sparse-reward env
(SignNav3D-v0) this tells a policy that never reaches a goal from one that reached it and forgot.
With ``--env SignNav3D-v0`` (or a path that names it) the pairs are labelled by the object they ask
for (the sign's colour, the instruction's type).
"""

from __future__ import annotations

import argparse
from typing import Callable, Optional

import numpy as np
from stable_baselines3.common.save_util import load_from_pkl

from sb3_dream.dream.buffers import DreamReplayBuffer, ExecutionRewardCounts


def pair_labeller(env_id: Optional[str]) -> Callable[[np.ndarray, np.ndarray], str]:
    """A name for a (problem features, instruction) pair: SignNav3D's target object, else the numbers."""
    if env_id == "SignNav3D-v0":
        from dream_envs.sign_nav import execution_target

        return lambda problem, instruction: " ".join(execution_target(problem[0], instruction))
    return lambda problem, instruction: f"problem {tuple(problem.tolist())} instruction {tuple(instruction.tolist())}"


def format_counts(counts: ExecutionRewardCounts, label: Callable[[np.ndarray, np.ndarray], str]) -> str:
    rows = [
        f"  {label(p, i):>24}: {n} transitions, {e} episodes, reward > 0 in {pos}, < 0 in {neg}, sum {s:+.2f}"
        for p, i, n, e, pos, neg, s in zip(
            counts.problem_features,
            counts.instructions,
            counts.transitions,
            counts.episodes,
            counts.positive,
            counts.negative,
            counts.reward_sum,
        )
    ]
    unlinked = f"  ({counts.unlinked} transitions whose exploration was overwritten: never sampled, not counted)"
    return "\n".join(rows + ([unlinked] if counts.unlinked else []))


def main(argv: Optional[list] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("buffer", help="a DREAM replay buffer (.pkl, from save_replay_buffer or a checkpoint)")
    parser.add_argument("--env", default=None, help="the env it was made on, to name the pairs (SignNav3D-v0)")
    args = parser.parse_args(argv)
    buffer = load_from_pkl(args.buffer)
    if not isinstance(buffer, DreamReplayBuffer):
        raise SystemExit(f"{args.buffer} holds a {type(buffer).__name__}, not a DREAM replay buffer")
    env_id = args.env or ("SignNav3D-v0" if "SignNav3D-v0" in args.buffer else None)
    print(f"{args.buffer}: {len(buffer.execution)} execution transitions")
    print(format_counts(buffer.execution_reward_counts(), pair_labeller(env_id)))


if __name__ == "__main__":
    main()
