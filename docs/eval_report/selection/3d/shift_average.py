"""Does reading a frame at several pixel shifts, each reading corrected by its shift's angle, and averaging them cut
the CMVAE's theta error near the image centre? One camera-only 3d episode's every third frame (seed 211), read
shifted by -2 to 2 pixels (edges replicated); prints the MAE and bias of each shift and of the averages.

    MUJOCO_GL=egl python docs/eval_report/selection/3d/shift_average.py encoder_service/models/cmvae_vertical.pt
"""

import sys

import numpy as np

from encoder_service.inference import LatentEncoder
from encoder_service.train import focal_length_px, shifted_frames
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker
from learner_service.task import TaskSettings

SHIFTS = (-2, -1, 0, 1, 2)


def loop_frames(encoder: LatentEncoder, steps: int = 3000, every: int = 3) -> tuple[np.ndarray, np.ndarray]:
    env = make_env("inprocess", TaskSettings(obs="cmvae", task="3d"), base_seed=211, encoder=encoder)
    tracker = LatentTracker(encoder.decode_state, encoder.n_z, TrackerGains(surge_gain=0.5))
    frames, azimuths = [], []
    obs, info = env.reset()
    for step in range(steps):
        if step % every == 0:
            frames.append(env.render().copy())
            azimuths.append(info["azimuth"])
        obs, _, terminated, truncated, info = env.step(tracker.act(obs, info))
        if terminated or truncated:
            break
    env.close()
    return np.stack(frames), np.array(azimuths)


def shift_averaged_reading(
    encoder: LatentEncoder, frames: np.ndarray, shifts: tuple[int, ...]
) -> tuple[np.ndarray, ...]:
    """(d, theta, elevation) of each frame: the means over its readings at ``shifts`` pixels (edges repeated), each
    theta corrected by its shift's angle (a dolphin moved right reads a smaller azimuth, + = left)."""
    focal_px = focal_length_px(frames.shape[2])
    moved = np.concatenate([shifted_frames(frames, np.full(len(frames), p)) for p in shifts])
    read = np.stack(encoder.decode_state(encoder.encode(moved)[0]))  # one batch: (labels, shifts * frames)
    d, theta, elevation = (read[column].reshape(len(shifts), len(frames)) for column in (0, 1, 3))
    theta = theta + np.degrees(np.arctan(np.array(shifts) / focal_px))[:, None]
    return d.mean(axis=0), theta.mean(axis=0), elevation.mean(axis=0)


def main() -> None:
    encoder = LatentEncoder(sys.argv[1])
    frames, azimuths = loop_frames(encoder)
    for name, shifts in [*((f"shift {p:+d}", (p,)) for p in SHIFTS), ("mean of -1..1", (-1, 0, 1)),
                         ("mean of -2..2", SHIFTS)]:  # fmt: skip
        error = shift_averaged_reading(encoder, frames, shifts)[1] - azimuths
        print(f"{name}: theta MAE {abs(error).mean():.3f} deg, bias {error.mean():+.3f} ({len(error)} frames)")


if __name__ == "__main__":
    main()
