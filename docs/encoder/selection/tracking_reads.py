"""How each CMVAE reads the dolphin while the rover follows it, rather than at an episode's first frame: one
clean episode of the ground-truth tracker on the selection seed (211), its frames read by every model. Beside
the errors, their jitter (the spread of one read's error minus the previous read's), which a late loop
amplifies, and the dolphin's heading (psi), on which the distance read leans (docs/encoder.md, "A low sun's
shafts in perspective").

    MUJOCO_GL=egl python docs/encoder/selection/tracking_reads.py OUT.csv CHECKPOINT [CHECKPOINT ...] [--split NAME]

``--split`` plays the episode in one held-out split's water and scenery (sim_service/splits.py) instead of clean.
"""

import argparse
from pathlib import Path

import numpy as np
from low_sun_ablation import SEED, write_table
from operating_point import tracked_frames

from encoder_service.inference import LatentEncoder
from sim_service.splits import resolve_splits

STEPS = 3000


def errors(encoder: LatentEncoder, frames: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    d, theta, psi = encoder.decode_state(encoder.encode(frames)[0])
    d_error, theta_error = d - truth[:, 0], theta - truth[:, 1]
    psi_error = (psi - truth[:, 2] + 180.0) % 360.0 - 180.0
    return {"d_mae_m": round(float(np.abs(d_error).mean()), 3),
            "d_bias_m": round(float(d_error.mean()), 3),
            "d_jitter_m": round(float(np.diff(d_error).std()), 3),
            "theta_mae_deg": round(float(np.abs(theta_error).mean()), 2),
            "theta_bias_deg": round(float(theta_error.mean()), 2),
            "theta_jitter_deg": round(float(np.diff(theta_error).std()), 2),
            "psi_mae_deg": round(float(np.abs(psi_error).mean()), 1)}  # fmt: skip


def arguments(description: str) -> argparse.Namespace:
    """OUT.csv, the checkpoints and --split, as this script and theta_by_heading.py take them."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("out")
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--split", help="a held-out split to track in (default: clean water)")
    return parser.parse_args()


def tracked_episode(split: str | None) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth tracker's episode on the selection seed, in clean water or in ``split``'s."""
    options = resolve_splits([split])[0].reset_options() if split else None
    return tracked_frames(SEED, episodes=1, steps=STEPS, every=1, options=options)


def main() -> None:
    args = arguments(__doc__.splitlines()[0])
    frames, truth = tracked_episode(args.split)
    about = {"water": args.split or "clean", "frames": len(frames)}
    rows = [{"checkpoint": Path(c).name, **about, **errors(LatentEncoder(c), frames, truth)} for c in args.checkpoints]
    write_table(args.out, rows, args.checkpoints)


if __name__ == "__main__":
    main()
