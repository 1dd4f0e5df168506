"""Where the azimuth read goes wrong while the rover follows: the theta error by the dolphin's heading (psi).

The ground-truth tracker holds the dolphin within a degree of the image centre, yet each CMVAE reads it there with
an error of a degree or more whose sign follows the dolphin's heading: seen going away one error, coming toward the
camera another. The reward's azimuth penalty is steepest there, so this is where a camera-only loop loses most of
its return (docs/encoder.md, "The azimuth read where the loop holds the dolphin"). One clean episode of the
ground-truth tracker on the selection seed (211), as `tracking_reads.py` plays it; rows by 30-degree psi bin.

    MUJOCO_GL=egl python docs/encoder/selection/theta_by_heading.py OUT.csv CHECKPOINT [CHECKPOINT ...] [--split NAME]
"""

from pathlib import Path

import numpy as np
from low_sun_ablation import write_table
from tracking_reads import arguments, tracked_episode

from encoder_service.inference import LatentEncoder

BIN_DEG = 30
MIN_FRAMES = 10  # a bin with fewer frames says nothing


def by_heading(encoder: LatentEncoder, frames: np.ndarray, truth: np.ndarray) -> list[dict]:
    _, theta, psi = encoder.decode_state(encoder.encode(frames)[0])
    theta_error = theta - truth[:, 1]
    psi_error = np.abs((psi - truth[:, 2] + 180.0) % 360.0 - 180.0)
    rows = [{"psi_from_deg": "all", "frames": len(frames), "theta_bias_deg": round(float(theta_error.mean()), 2),
             "theta_mae_deg": round(float(np.abs(theta_error).mean()), 2),
             "psi_mae_deg": round(float(psi_error.mean()), 1)}]  # fmt: skip
    for start in range(-180, 180, BIN_DEG):
        inside = (truth[:, 2] >= start) & (truth[:, 2] < start + BIN_DEG)
        if inside.sum() >= MIN_FRAMES:
            rows.append({"psi_from_deg": start, "frames": int(inside.sum()),
                         "theta_bias_deg": round(float(theta_error[inside].mean()), 2),
                         "theta_mae_deg": round(float(np.abs(theta_error[inside]).mean()), 2),
                         "psi_mae_deg": round(float(psi_error[inside].mean()), 1)})  # fmt: skip
    return rows


def main() -> None:
    args = arguments(__doc__.splitlines()[0])
    frames, truth = tracked_episode(args.split)
    rows = []
    for checkpoint in args.checkpoints:
        about = {"checkpoint": Path(checkpoint).name, "water": args.split or "clean"}
        rows += [{**about, **row} for row in by_heading(LatentEncoder(checkpoint), frames, truth)]
    write_table(args.out, rows, args.checkpoints)


if __name__ == "__main__":
    main()
