"""Does reading a frame at several pixel shifts, each reading corrected by its shift's angle, and averaging them cut
the CMVAE's theta error near the image centre? One camera-only 3d episode's every third frame (seed 211), read
shifted by -2 to 2 pixels (edges replicated); prints the MAE and bias of each shift and of the averages.

    MUJOCO_GL=egl python docs/eval_report/selection/3d/shift_average.py encoder_service/models/cmvae_vertical.pt
"""

import math
import sys

import numpy as np

from encoder_service.inference import LatentEncoder
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker
from learner_service.task import TaskSettings
from services.geometry import ALPHA_DEG

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


def shifted(frames: np.ndarray, pixels: int) -> np.ndarray:
    """Frames moved ``pixels`` columns to the right (left if negative), the edge column repeated."""
    out = np.roll(frames, pixels, axis=2)
    if pixels > 0:
        out[:, :, :pixels] = frames[:, :, :1]
    elif pixels < 0:
        out[:, :, pixels:] = frames[:, :, -1:]
    return out


def main() -> None:
    encoder = LatentEncoder(sys.argv[1])
    frames, azimuths = loop_frames(encoder)
    focal_px = frames.shape[2] / 2 / math.tan(math.radians(ALPHA_DEG))
    reads = {}
    for pixels in SHIFTS:
        mu, _ = encoder.encode(shifted(frames, pixels))
        # A dolphin moved right reads a smaller azimuth (+ = left): add the shift's angle back.
        reads[pixels] = encoder.decode_state(mu)[1] + math.degrees(math.atan(pixels / focal_px))
    for name, shifts in [*((f"shift {p:+d}", (p,)) for p in SHIFTS), ("mean of -1..1", (-1, 0, 1)),
                         ("mean of -2..2", SHIFTS)]:  # fmt: skip
        error = np.mean([reads[p] for p in shifts], axis=0) - azimuths
        print(f"{name}: theta MAE {abs(error).mean():.3f} deg, bias {error.mean():+.3f} ({len(error)} frames)")


if __name__ == "__main__":
    main()
