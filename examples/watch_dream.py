"""Watch a trained DREAM model: a video of one trial, its exploration episode then its execution.

    python examples/watch_dream.py --model dream_metabus.zip --out dream_metabus.mp4
    python examples/watch_dream.py --model dream_map.zip --env-kwargs variant=map --out map.gif
    python examples/watch_dream.py --oracle --out oracle.mp4     # the env's optimal scripted agent

The trial runs on a held-out problem (``--split test``, ``--problem-id`` to pin one). Each frame
is the env's own ``render()`` picture (which names the phase, the step and the instruction) under a
banner with the action taken and the reward; a title card separates the exploration episode
(reward-free: watch what DREAM looks at) from the execution episodes (watch it use what it saw).
Videos are written with OpenCV only: ``.mp4`` (``cv2.VideoWriter``, codec mp4v), ``.avi`` (MJPG)
or an animated ``.gif`` (``cv2.imwriteanimation``, OpenCV >= 4.11; imageio is used for GIFs on
older OpenCV if it is installed).
"""

from __future__ import annotations

import argparse
import pathlib
from typing import Any, Dict, List, Optional, Sequence

import cv2
import gymnasium as gym
import numpy as np

import dream_envs
from dream_envs import EXPLORATION, ScriptedAgent, public_info
from sb3_dream.common.files import atomic_target
from sb3_dream.experiments import parse_kwargs

# Action names of the grid families (MetaBus-v0, MetaCook-v0 share the action set).
GRID_ACTIONS = ("left", "up", "right", "down", "no-op", "ride bus", "end episode", "pickup", "drop")
BANNER = 36  # pixels of text above each frame


def action_name(env_id: str, action: int) -> str:
    if env_id.split(":")[-1] in ("MetaBus-v0", "MetaCook-v0"):
        return GRID_ACTIONS[action]
    return f"action {action}"


def with_banner(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` (RGB) under a white strip holding ``text``."""
    strip = np.full((BANNER, frame.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (8, BANNER - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (20, 20, 20), 1, cv2.LINE_AA)
    return np.concatenate([strip, frame], axis=0)


def title_card(shape: Sequence[int], lines: Sequence[str]) -> np.ndarray:
    """A dark frame of ``shape`` with ``lines`` of white text, centred."""
    card = np.full(shape, 40, np.uint8)
    height = shape[0]
    for k, line in enumerate(lines):
        (width, _), _ = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, 0.7, 2)
        y = height // 2 + (k - (len(lines) - 1) / 2) * 34
        cv2.putText(
            card,
            line,
            ((shape[1] - width) // 2, int(y)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.7,
            (255, 255, 255),
            2,
            cv2.LINE_AA,
        )
    return card


def record_trial(
    env: gym.Env, agent: ScriptedAgent, env_id: str, seed: int, options: Optional[Dict[str, Any]], hold: int
) -> tuple[List[np.ndarray], List[float], int]:
    """Play one trial and return its frames, the execution returns and the exploration length.

    The agent sees what :func:`dream_envs.play_trial` shows it: observations and the public info.
    """
    agent.reset()
    obs, info = env.reset(seed=seed, options=options)
    frame = env.render()
    frames = [title_card(with_banner(frame, "").shape, ["Exploration episode", "reward-free, no instruction"])] * hold
    frames.append(with_banner(frame, "start"))
    returns: List[float] = []
    exploration_length, episode_return = 0, 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        action = agent.act(obs, public_info(info))
        obs, reward, terminated, truncated, info = env.step(action)
        episode_return += float(reward)
        text = f"{action_name(env_id, action)}   reward {reward:+.2f}   return {episode_return:+.2f}"
        if info.get("episode_end"):
            # The step already shows the next episode's start; the banner tells how this one ended.
            if info["episode_phase"] == EXPLORATION:
                exploration_length = info["episode_length"]
                text = f"{action_name(env_id, action)}   exploration over after {exploration_length} steps"
            else:
                returns.append(info["episode_return"])
                text = f"{action_name(env_id, action)}   episode return {info['episode_return']:+.2f}"
            frames += [with_banner(info["final_frame"], text)] * hold  # the episode's last state, held
            episode_return = 0.0
            if not terminated:
                index = info["episode_index"]
                instruction = np.asarray(obs["instruction"]).tolist()
                card = ["Execution episode %d" % index, f"instruction {instruction}"]
                frames += [title_card(frames[-1].shape, card)] * hold
                frames.append(with_banner(env.render(), "start"))
            continue
        frames.append(with_banner(env.render(), text))
    return frames, returns, exploration_length


def write_video(frames: Sequence[np.ndarray], path: pathlib.Path, fps: int) -> None:
    """Write RGB ``frames`` to ``path`` (.mp4, .avi or .gif) with OpenCV, through a temporary file
    renamed over ``path`` once it is complete."""
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".avi", ".gif"):
        raise ValueError(f"out={str(path)!r} is not valid; accepted suffixes: '.mp4', '.avi', '.gif'")
    with atomic_target(path, suffix[1:]) as tmp:
        if suffix in (".mp4", ".avi"):
            height, width = frames[0].shape[:2]
            fourcc = cv2.VideoWriter_fourcc(*("mp4v" if suffix == ".mp4" else "MJPG"))
            writer = cv2.VideoWriter(str(tmp), fourcc, fps, (width, height))
            if not writer.isOpened():
                raise RuntimeError(f"OpenCV cannot write {suffix} here: try --out with .avi or .gif")
            for frame in frames:
                writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            writer.release()
        elif hasattr(cv2, "imwriteanimation"):  # OpenCV >= 4.11
            animation = cv2.Animation()
            animation.frames = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in frames]
            animation.durations = [int(1000 / fps)] * len(frames)
            if not cv2.imwriteanimation(str(tmp), animation):
                raise RuntimeError(f"OpenCV could not write {path}")
        else:
            try:
                import imageio.v2 as imageio
            except ImportError as error:
                raise RuntimeError("GIFs need OpenCV >= 4.11 or imageio: write an .mp4 instead") from error
            imageio.mimsave(tmp, list(frames), duration=1 / fps)


def load_agent(args: argparse.Namespace, env: gym.Env) -> ScriptedAgent:
    if args.oracle:
        return dream_envs.make_oracle(env)
    from sb3_dream import DREAM

    model = DREAM.load(args.model, device="cpu")
    # as_trial_agent also hands DREAM the exploration's last state (info["final_obs"]) for z = g(tau).
    return model.as_trial_agent(deterministic=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", help="a saved DREAM model (.zip)")
    source.add_argument("--oracle", action="store_true", help="watch the env's optimal scripted agent instead")
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="e.g. variant=map")
    parser.add_argument("--split", default="test", choices=dream_envs.all_splits())
    parser.add_argument("--problem-id", type=int, default=None, help="pin the problem (default: drawn from --seed)")
    parser.add_argument("--n-exec-episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fps", type=int, default=4)
    parser.add_argument(
        "--hold", type=int, default=None, help="frames to hold title cards and episode ends (default: fps)"
    )
    parser.add_argument("--out", default="dream_trial.mp4", help=".mp4, .avi or .gif")
    args = parser.parse_args()

    env_kwargs = parse_kwargs(args.env_kwargs, "--env-kwargs")
    env = gym.make(
        args.env,
        split=args.split,
        n_exec_episodes=args.n_exec_episodes,
        render_mode="rgb_array",
        final_frames=True,  # each inner episode's last state, which the step has already left
        **env_kwargs,
    )
    agent = load_agent(args, env)
    options = None if args.problem_id is None else {"problem_id": args.problem_id}
    frames, returns, length = record_trial(env, agent, args.env, args.seed, options, hold=args.hold or args.fps)
    out = pathlib.Path(args.out)
    write_video(frames, out, args.fps)
    print(
        f"wrote {out} ({len(frames)} frames): exploration {length} steps, execution returns "
        + ", ".join(f"{r:+.2f}" for r in returns)
    )


if __name__ == "__main__":
    main()
