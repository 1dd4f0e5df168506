"""A sample dive video for `swimm pilot --dry-run`: the scripted tracker following the dolphin, filmed by the sim's
camera at a size a real camera's stream would be scaled to.

    python -m eval_service.sample_video --out pilot_service/samples/dive.mp4

The ground-truth scripted tracker flies (so the dolphin stays in view), the world renders ``--size`` pixels
square (the sim camera's 79.95 degree field: fly the pilot with ``--camera-hfov-deg 79.95``), and every
``--every``-th 50 Hz step becomes a frame of an MPEG-4 file at 50/every frames a second.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2

from learner_service.inprocess_env import TrackingEnv
from learner_service.registry import load_policy
from learner_service.task import TaskSettings
from sim_service.settings import WorldSettings

PHYSICS_HZ = 50


def write_video(out: Path, seconds: float, size: int, every: int, seed: int) -> int:
    """Film the tracker for ``seconds``; returns the number of frames written."""
    env = TrackingEnv(TaskSettings(obs="state", early_termination=False), WorldSettings(image_size=size),
                      base_seed=seed)  # fmt: skip
    policy = load_policy("scripted", None)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), PHYSICS_HZ / every, (size, size))
    frames = 0
    try:
        obs, info = env.reset()
        for step in range(round(seconds * PHYSICS_HZ)):
            obs, _, _, _, info = env.step(policy.act(obs, info))
            if step % every == 0:
                writer.write(cv2.cvtColor(env.render(), cv2.COLOR_RGB2BGR))
                frames += 1
    finally:
        writer.release()
        env.close()
    return frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="pilot_service/samples/dive.mp4")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--size", type=int, default=160)
    parser.add_argument("--every", type=int, default=2, help="50 Hz steps per frame (2: a 25 fps film)")
    parser.add_argument("--seed", type=int, default=9001)
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    frames = write_video(Path(args.out), args.seconds, args.size, args.every, args.seed)
    print(f"wrote {frames} frames to {args.out}")


if __name__ == "__main__":
    main()
