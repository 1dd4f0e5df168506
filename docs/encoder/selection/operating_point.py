"""How CMVAEs read the dolphin where the tracker holds it (about 6 m ahead, near the centre), plain and mirror-averaged.

The ground-truth scripted tracker plays two clean episodes of 600 steps from seed 211 (the selection seed); every
third frame is read by each CMVAE given, as it is and averaged with its mirror image (``--mirror-average``: theta
and psi of the mirror negated). Bias and MAE of d and theta against the truth go to a CSV. Reset frames (the
suite's encoder check) sample the whole field of view; these are the frames a closed loop sees.

    MUJOCO_GL=egl python docs/encoder/selection/operating_point.py --out docs/encoder/selection/operating-point.csv \
        encoder_service/models/cmvae_general.pt encoder_service/models/cmvae_light.pt runs/l3/best.pt
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from encoder_service.inference import LatentEncoder
from learner_service.inprocess_env import TrackingEnv, task_world
from learner_service.scripted import ScriptedTracker
from learner_service.task import TaskSettings
from services.results import provenance, write_provenance_beside


def tracked_frames(
    seed: int, episodes: int, steps: int, every: int, options: dict | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Frames (N, 64, 64, 3) with the true (d, azimuth, psi) of each, from the ground-truth tracker's episodes:
    clean, or in the water and scenery of each reset's ``options`` (a suite split's ``reset_options()``)."""
    settings = TaskSettings(obs="state")
    env = TrackingEnv(settings, task_world(settings, render=True), base_seed=seed)
    tracker = ScriptedTracker()
    frames, truth = [], []
    for _ in range(episodes):
        obs, info = env.reset(options=options)
        for step in range(steps):
            obs, _, terminated, truncated, info = env.step(tracker.act(obs, info))
            if step % every == 0:
                frames.append(env.render().copy())
                truth.append((info["d"], info["azimuth"], info["psi"]))
            if terminated or truncated:
                break
    env.close()
    return np.stack(frames), np.array(truth)


def readings(encoder: LatentEncoder, frames: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """d and theta as read from each frame, and averaged with the mirror image's reading (theta negated)."""
    d, theta, *_ = encoder.decode_state(encoder.encode(frames)[0])
    d_mirror, theta_mirror, *_ = encoder.decode_state(encoder.encode(np.ascontiguousarray(frames[:, :, ::-1]))[0])
    return {"plain": (d, theta), "mirror-averaged": ((d + d_mirror) / 2, (theta - theta_mirror) / 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=211)
    args = parser.parse_args()
    frames, truth = tracked_frames(args.seed, episodes=2, steps=600, every=3)
    d_true, azimuth_true = truth[:, 0], truth[:, 1]
    rows = []
    for checkpoint in args.checkpoints:
        for reading, (d, theta) in readings(LatentEncoder(checkpoint), frames).items():
            rows.append({"checkpoint": checkpoint, "reading": reading, "frames": len(frames),
                         "d_bias_m": float(np.mean(d - d_true)), "d_mae_m": float(np.mean(abs(d - d_true))),
                         "theta_bias_deg": float(np.mean(theta - azimuth_true)),
                         "theta_mae_deg": float(np.mean(abs(theta - azimuth_true)))})  # fmt: skip
            print({key: round(value, 3) if isinstance(value, float) else value for key, value in rows[-1].items()})
    with args.out.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    write_provenance_beside(args.out, provenance({Path(c).name: c for c in args.checkpoints}, seeds=[args.seed]))


if __name__ == "__main__":
    main()
