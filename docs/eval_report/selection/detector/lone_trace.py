"""One episode of the camera-only tracker on a detector, a lone dolphin in one suite condition: every 25th step's
reward, live tracks, and the target track's misses, azimuth and distance against the truth (docs/encoder.md, "A
detector for a lone dolphin"). A diagnostic, not a result:

    MUJOCO_GL=egl python docs/eval_report/selection/detector/lone_trace.py runs/det-aug.pt sensor --seed 211
"""

from __future__ import annotations

import argparse

import numpy as np

from encoder_service.pod_encoder import PodEncoder
from learner_service.inprocess_env import TrackingEnv, task_world
from learner_service.registry import load_policy
from learner_service.task import TaskSettings
from services.pod_tracker import ALIVE, AZIMUTH, FIELDS, LOG_D, MAX_TRACKS, MISSES, TARGET
from sim_service.settings import WorldSettings
from sim_service.splits import resolve_splits


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detector")
    parser.add_argument("split", help="a held-out split's name (sim_service/splits.py)")
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()
    (split,) = resolve_splits([args.split])
    task = TaskSettings(obs="cmvae", max_steps=args.steps)
    env = TrackingEnv(task, task_world(task, base=WorldSettings()), base_seed=args.seed,
                      encoder=PodEncoder(args.detector))  # fmt: skip
    policy = load_policy("scripted-camera", args.detector)
    obs, info = env.reset(options=split.reset_options())
    for step in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(policy.act(obs, info))
        tracks = env._prior.reshape(MAX_TRACKS, len(FIELDS))  # the tracker state the env carries to the next frame
        target = tracks[np.argmax(tracks[:, TARGET])]
        if step % 25 == 0 or terminated:
            print(f"step {step:5d} reward {reward:+.2f} tracks {int(tracks[:, ALIVE].sum())} misses "
                  f"{target[MISSES]:.0f} azimuth {target[AZIMUTH]:+6.1f} / {info['theta']:+6.1f} deg, distance "
                  f"{np.exp(target[LOG_D]):5.2f} / {info['d']:5.2f} m (read / true)")  # fmt: skip
        if terminated or truncated:
            break


if __name__ == "__main__":
    main()
