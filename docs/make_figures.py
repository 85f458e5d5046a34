"""Render a picture of each env with the project's own renderer: ``python docs/make_figures.py``.

Each picture shows a trial in progress: the oracle is played for a few steps of its first
execution episode (after its exploration), so the picture shows the instruction and the agent;
with 0 steps, the picture is the last moment of exploration (the 3D env: reading the sign).
Writes ``docs/<env>.png``.
"""

from __future__ import annotations

import argparse
import pathlib

import cv2
import gymnasium as gym

import dream_envs
from dream_envs import EXECUTION, public_info

PICTURES = {
    "metabus": ("MetaBus-v0", {}, 1),
    "metabus_map": ("MetaBus-v0", {"variant": "map"}, 1),
    "metacook": ("MetaCook-v0", {}, 3),
    "signnav3d": ("SignNav3D-v0", {}, 0),  # 0: the moment exploration reads the sign
    "metabandit": ("MetaBandit-v0", {"n_actions": 4, "horizon": 3}, 2),
}


def picture(env_id: str, kwargs: dict, exec_steps: int, seed: int):
    env = gym.make(env_id, render_mode="rgb_array", **kwargs)
    oracle = dream_envs.make_oracle(env)
    oracle.reset()
    obs, info = env.reset(seed=seed)
    steps_in_execution = 0
    while steps_in_execution < exec_steps or exec_steps == 0:
        action = oracle.act(obs, public_info(info))
        if exec_steps == 0 and action == env.unwrapped.end_episode_action:
            break
        obs, _, terminated, _, info = env.step(action)
        if terminated:
            break
        if obs["phase"] == EXECUTION:
            steps_in_execution += 1
    frame = env.render()
    env.close()
    return frame


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent), help="output folder")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, (env_id, kwargs, steps) in PICTURES.items():
        frame = picture(env_id, kwargs, steps, args.seed)
        path = out / f"{name}.png"
        cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        print(f"wrote {path} {frame.shape}")


if __name__ == "__main__":
    main()
