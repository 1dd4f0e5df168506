"""How the CMVAE's reads go wrong in the camera-only tracker's closed loop under the low sun: spikes a filter could
remove, or errors that last? Three episodes of 3000 steps (seed 211), the tracker acting on the read; prints, per
episode, the return, the theta and d read errors, how long theta's errors above 5 deg last, and what a causal
median of the last k reads would leave.

    MUJOCO_GL=egl python docs/encoder/selection/low_sun_loop.py encoder_service/models/cmvae_wide.pt
"""

import sys

import numpy as np

from encoder_service.inference import LatentEncoder
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker
from learner_service.task import TaskSettings
from sim_service.splits import SPLITS

EPISODES, STEPS, SEED = 3, 3000, 211
MEDIAN_WINDOWS = (3, 5, 9)


def play(encoder: LatentEncoder, env, tracker: LatentTracker) -> tuple[float, np.ndarray]:
    """One episode's return and its steps' (true d, read d, true azimuth, read azimuth)."""
    obs, info = env.reset(options=SPLITS["low-sun"].reset_options())
    total, rows = 0.0, []
    for _ in range(STEPS):
        read_d, read_theta, *_ = encoder.decode_state(np.asarray(obs, dtype=np.float32)[None, : encoder.n_z])
        rows.append((info["d"], float(read_d[0]), info["azimuth"], float(read_theta[0])))
        obs, reward, terminated, truncated, info = env.step(tracker.act(obs, info))
        total += float(reward)
        if terminated or truncated:
            break
    return total, np.array(rows)


def causal_median(values: np.ndarray, window: int) -> np.ndarray:
    return np.array([np.median(values[max(0, i - window + 1) : i + 1]) for i in range(len(values))])


def main() -> None:
    encoder = LatentEncoder(sys.argv[1])
    task = TaskSettings(obs="cmvae", max_steps=STEPS, early_termination=False)
    env = make_env("inprocess", task, base_seed=SEED, encoder=encoder)
    tracker = LatentTracker(encoder.decode_state, encoder.n_z, TrackerGains())
    for episode in range(EPISODES):
        total, rows = play(encoder, env, tracker)
        d, read_d, azimuth, read_theta = rows.T
        error = read_theta - azimuth
        large = np.abs(error) > 5.0
        edges = np.flatnonzero(np.diff(np.r_[0, large.astype(int), 0]))
        stretches = edges[1::2] - edges[::2]
        medians = ", ".join(f"{w}: {np.abs(causal_median(read_theta, w) - azimuth).mean():.2f}" for w in MEDIAN_WINDOWS)
        print(f"episode {episode}: return {total:.1f}; theta read MAE {np.abs(error).mean():.2f} deg, lag-1 "
              f"autocorrelation {np.corrcoef(error[:-1], error[1:])[0, 1]:.2f}, above 5 deg on {large.mean():.1%} of "
              f"steps in {len(stretches)} stretches of {stretches.mean():.1f} steps on average; causal median of k "
              f"reads, theta MAE {medians}; d read MAE {np.abs(read_d - d).mean():.2f} m, bias "
              f"{(read_d - d).mean():+.2f} m, true d mean {d.mean():.2f} m, true |azimuth| mean "
              f"{np.abs(azimuth).mean():.2f} deg")  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
