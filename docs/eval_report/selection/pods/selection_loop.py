"""Selection runs of pod tracker settings on a detector: return and identity metrics per split, on the same episodes
as `swimm eval` (no early termination; docs/encoder.md, "Where identity goes in the plain split"). A diagnostic,
not a result. It ran at commit 4e46d3d for the shade spreads (tries/shade-spread-sweep.jsonl, detector
runs/det-shade.pt) and, for the nearer-detection gate (tries/nearer-gate-sweep.jsonl), on that tracker with a
``target_nearer_limit`` field never committed. The look cue's sweep (tries/look-sweep.jsonl) ran on the tracker of
commit b76982d (its ``look_sigma`` and ``look_memory``; the 3x3-mean rows with pixel_looks reading the window's mean);
``{"look_sigma": 0}`` there and since plays the tracker without the cue. ``--params`` takes TrackerParams' fields as
they are at HEAD:

    MUJOCO_GL=egl LP_NUM_THREADS=0 python docs/eval_report/selection/pods/selection_loop.py \
        --detector encoder_service/models/pod_detector.pt --crossing --params '{"log_d_sigma": 0.2}'
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from encoder_service.pod_encoder import PodEncoder
from learner_service.inprocess_env import TrackingEnv, task_world
from learner_service.registry import load_policy
from learner_service.task import TaskSettings
from services.identity import episode_identity
from services.pod_tracker import PodTracker, TrackerParams
from sim_service.settings import DolphinSettings, WorldSettings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detector", required=True)
    parser.add_argument("--crossing", action="store_true")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--params", default="{}", help="TrackerParams fields as JSON")
    args = parser.parse_args()
    params = json.loads(args.params)
    task = TaskSettings(obs="cmvae", max_steps=3000, early_termination=False)  # as swimm eval plays episodes
    world = task_world(task, base=WorldSettings(dolphin=DolphinSettings(pod_size=4, pod_crossing=args.crossing)))
    encoder = PodEncoder(args.detector, tracker=PodTracker(TrackerParams(**params)), threads=1)
    env = TrackingEnv(task, world, base_seed=args.seed, encoder=encoder)
    policy = load_policy("scripted-camera", args.detector)
    returns, metrics = [], []
    for _ in range(args.episodes):
        obs, info = env.reset()
        followed, occluded, episode_return = [], [], 0.0
        for _ in range(task.max_steps):
            obs, reward, terminated, truncated, info = env.step(policy.act(obs, info))
            episode_return += reward
            followed.append(info["telemetry"].followed)
            occluded.append(info["telemetry"].target_occluded)
            if terminated or truncated:
                break
        returns.append(episode_return)
        metrics.append(episode_identity(followed, occluded))
    print(json.dumps({
        "params": params, "crossing": args.crossing, "ret": round(float(np.mean(returns)), 1),
        "share": round(float(np.nanmean([m["identity_share"] for m in metrics])), 3),
        "kept": int(sum(m["identity_kept"] for m in metrics)),
        "switches": round(float(np.mean([m["switches"] for m in metrics])), 2),
        "returns": [round(value) for value in returns],
    }))  # fmt: skip


if __name__ == "__main__":
    main()
