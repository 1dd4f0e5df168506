"""One episode of the camera-only tracker on the pod detector, step by step: what the tracker holds as the target
against the ground truth, and a line per stretch in which a companion hides the target (docs/encoder.md, "Every
dolphin, then which one"). A diagnostic, not a result:

    MUJOCO_GL=egl python docs/eval_report/selection/pods/crossing_trace.py --crossing --seed 211 \
        --out docs/eval_report/selection/pods/crossing-trace
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from encoder_service.pod_encoder import PodEncoder
from learner_service.inprocess_env import TrackingEnv, task_world
from learner_service.registry import load_policy
from learner_service.task import TaskSettings
from services.pod_tracker import AZIMUTH, BEHIND, FIELDS, LOG_D, MAX_TRACKS, MISSES, TARGET
from sim_service.settings import DolphinSettings, WorldSettings

DETECTOR = "encoder_service/models/pod_detector.pt"
COLUMNS = ("step", "reward", "followed", "occluded", "behind", "misses", "tracker_az", "tracker_d", "true_az", "true_d")


def play(crossing: bool, seed: int, steps: int) -> np.ndarray:
    task = TaskSettings(obs="cmvae", max_steps=steps)
    world = task_world(task, base=WorldSettings(dolphin=DolphinSettings(pod_size=4, pod_crossing=crossing)))
    env = TrackingEnv(task, world, base_seed=seed, encoder=PodEncoder(DETECTOR))
    policy = load_policy("scripted-camera", DETECTOR)
    obs, info = env.reset()
    rows = []
    for step in range(steps):
        obs, reward, terminated, truncated, info = env.step(policy.act(obs, info))
        tracks = env._prior.reshape(MAX_TRACKS, len(FIELDS))  # the tracker state the env carries to the next frame
        target = tracks[np.argmax(tracks[:, TARGET])]
        telemetry = info["telemetry"]
        rows.append((step, reward, telemetry.followed, telemetry.target_occluded, target[BEHIND], target[MISSES],
                     target[AZIMUTH], np.exp(target[LOG_D]), info["theta"], info["d"]))  # fmt: skip
        if terminated or truncated:
            break
    return np.array(rows, dtype=float)


def stretches(rows: np.ndarray) -> list[str]:
    """A line per stretch of occluded steps: how many the tracker held behind, who is followed after it."""
    col = {name: index for index, name in enumerate(COLUMNS)}
    occluded = rows[:, col["occluded"]] > 0
    starts = np.nonzero(np.diff(occluded.astype(int)) > 0)[0] + 1
    lines = []
    for start in starts:
        end = start + int(np.argmax(~occluded[start:])) if (~occluded[start:]).any() else len(rows)
        after = rows[min(end + 30, len(rows) - 1)]
        lines.append(
            f"steps {start}-{end}: held behind on {rows[start:end, col['behind']].sum():.0f}; target azimuth "
            f"(tracker / true) {rows[start, col['tracker_az']]:.1f} / {rows[start, col['true_az']]:.1f} deg at the "
            f"start, {rows[end - 1, col['tracker_az']]:.1f} / {rows[end - 1, col['true_az']]:.1f} at the end; "
            f"followed 30 steps later: {'the target' if after[col['followed']] == 0 else 'a companion'}"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--crossing", action="store_true")
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.csv and OUT.txt")
    args = parser.parse_args()
    rows = play(args.crossing, args.seed, args.steps)
    np.savetxt(args.out.with_suffix(".csv"), rows, fmt="%.3f", delimiter=",", header=",".join(COLUMNS), comments="")
    summary = [f"{len(rows)} steps, return {rows[:, 1].sum():.1f}, occluded {rows[:, 3].sum():.0f}, "
               f"held behind {rows[:, 4].sum():.0f}", *stretches(rows)]  # fmt: skip
    args.out.with_suffix(".txt").write_text("\n".join(summary) + "\n")
    print("\n".join(summary))


if __name__ == "__main__":
    main()
