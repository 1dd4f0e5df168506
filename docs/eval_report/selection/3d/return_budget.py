"""Where a 3d tracker's return goes: each reward term's sum over an episode, and the CMVAE's reading errors in the
closed loop (the frames the tracker holds the dolphin in, not reset frames).

The 3d task's reward per step is 1 less a distance, an azimuth and an elevation penalty (learner_service/task.py);
this plays the ground-truth or the camera-only scripted tracker in process and sums each penalty apart, beside the
true azimuth and elevation it holds and the CMVAE's bias, MAE and lag-1 autocorrelation of its theta error.
Appends one row per episode to a CSV (docs/learner.md, "Where the 3d camera tracker's return goes").

    MUJOCO_GL=egl python docs/eval_report/selection/3d/return_budget.py OUT.csv --tracker camera \
        --checkpoint encoder_service/models/cmvae_vertical.pt --episodes 3 --seed 211

With ``--detector FILE`` the CMVAE's azimuth is the pod detector's tracked reading instead
(docs/encoder/selection/fused_suite.py).
"""

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from shift_average import shift_averaged_reading

from encoder_service.inference import LatentEncoder
from learner_service.envs import make_env
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker, ScriptedTracker
from learner_service.task import TaskSettings, swimm2_elevation_penalty, swimm2_penalties
from services.results import provenance, write_provenance_beside
from sim_service.settings import WorldSettings, world_of_file


def play(env, encoder: LatentEncoder, tracker, steps: int, shifts: tuple[int, ...] = ()) -> np.ndarray:
    """(true d, azimuth, elevation, read d, theta, elevation) of every step of one episode. With ``shifts`` the
    readings (and the camera tracker's commands) are the means over the frame read at those pixel shifts, each
    theta corrected by its shift's angle (shift_average.py); without, the observation's latent."""
    obs, info = env.reset()
    rows = []
    for _ in range(steps):
        if shifts:
            read_d, read_theta, read_elevation = (
                float(v[0]) for v in shift_averaged_reading(encoder, env.render()[None], shifts)
            )
        else:
            latent = np.asarray(obs, np.float32)[None, : encoder.n_z]
            read_d, read_theta, _, read_elevation = (float(v[0]) for v in encoder.decode_state(latent))
        rows.append((info["d"], info["azimuth"], info["elevation"], read_d, read_theta, read_elevation))
        if shifts and isinstance(tracker, LatentTracker):
            action = tracker.command(read_d, read_theta, obs, read_elevation)
        else:
            action = tracker.act(obs, info)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    return np.array(rows)


def budget(rows: np.ndarray) -> dict[str, float]:
    d, azimuth, elevation, read_d, read_theta, read_elevation = rows.T
    pen_d, pen_theta = np.array([swimm2_penalties(*step) for step in zip(d, abs(azimuth), strict=True)]).T
    pen_elevation = np.array([swimm2_elevation_penalty(abs(e)) for e in elevation])
    theta_error = read_theta - azimuth
    return {
        "steps": len(rows),
        "return": float((1 - pen_d - pen_theta - pen_elevation).sum()),
        "distance_penalty": float(pen_d.sum()),
        "azimuth_penalty": float(pen_theta.sum()),
        "elevation_penalty": float(pen_elevation.sum()),
        "mean_abs_azimuth_deg": float(abs(azimuth).mean()),
        "mean_abs_elevation_deg": float(abs(elevation).mean()),
        "mean_d_m": float(d.mean()),
        "theta_read_bias_deg": float(theta_error.mean()),
        "theta_read_mae_deg": float(abs(theta_error).mean()),
        "theta_read_lag1_autocorr": float(np.corrcoef(theta_error[:-1], theta_error[1:])[0, 1]),
        "d_read_bias_m": float((read_d - d).mean()),
        "elevation_read_mae_deg": float(abs(read_elevation - elevation).mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--tracker", choices=["camera", "ground-truth"], required=True)
    parser.add_argument("--checkpoint", default="encoder_service/models/cmvae_vertical.pt")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--surge-gain", type=float, default=0.5)
    parser.add_argument("--yaw-gain", type=float, default=TrackerGains.yaw_gain)
    parser.add_argument("--yaw-damping", type=float, default=TrackerGains.yaw_damping)
    parser.add_argument("--heave-gain", type=float, default=TrackerGains.heave_gain)
    parser.add_argument("--heave-dead-band", type=float, default=TrackerGains.heave_dead_band)
    parser.add_argument("--shifts", type=int, nargs="*", default=[], help="read each frame at these pixel shifts")
    parser.add_argument("--sim-config", help="the world of a `swimm sim` settings file (default: the plain world)")
    parser.add_argument("--render-scale", type=int, help="render this many times larger, then downsample")
    parser.add_argument("--detector", help="a pod detector whose tracked azimuth replaces the CMVAE's")
    args = parser.parse_args()
    if args.detector:
        # another folder's diagnostic (docs/encoder/selection), on sys.path only when asked for
        sys.path.insert(0, str(Path(__file__).parents[3] / "encoder" / "selection"))
        from fused_suite import DetectorReading

        encoder = DetectorReading(args.checkpoint, args.detector, "azimuth")
    else:
        encoder = LatentEncoder(args.checkpoint)
    world = world_of_file(args.sim_config) if args.sim_config else WorldSettings()
    if args.render_scale is not None:  # else the settings file's, so a file that sets it is not overridden
        world = replace(world, render_scale=args.render_scale)
    task = TaskSettings(obs="cmvae", task="3d")
    env = make_env("inprocess", task, base_seed=args.seed, encoder=encoder, world=world)
    gains = TrackerGains(
        surge_gain=args.surge_gain,
        yaw_gain=args.yaw_gain,
        yaw_damping=args.yaw_damping,
        heave_gain=args.heave_gain,
        heave_dead_band=args.heave_dead_band,
    )
    tracker = (
        LatentTracker(encoder.decode_state, encoder.n_z, gains) if args.tracker == "camera" else ScriptedTracker(gains)
    )
    rows = []
    try:
        for episode in range(1, args.episodes + 1):
            rows.append(
                {
                    "tracker": args.tracker,
                    "checkpoint": Path(args.checkpoint).name
                    + (f"+{Path(args.detector).name}" if args.detector else ""),
                    "seed": args.seed,
                    "episode": episode,
                    "surge_gain": args.surge_gain,
                    "yaw_gain": args.yaw_gain,
                    "yaw_damping": args.yaw_damping,
                    "heave_gain": args.heave_gain,
                    "heave_dead_band": args.heave_dead_band,
                    "shifts": " ".join(map(str, args.shifts)),
                    "sim_config": args.sim_config or "",
                    "render_scale": world.render_scale,
                    **budget(play(env, encoder, tracker, args.steps, tuple(args.shifts))),
                }
            )
            print({k: round(v, 3) if isinstance(v, float) else v for k, v in rows[-1].items()}, flush=True)
    finally:
        env.close()
    table = pd.DataFrame(rows)
    out = args.out
    if out.is_file() and list(pd.read_csv(out, nrows=0).columns) != list(table.columns):
        # an older file's columns would misalign the appended rows: keep the episodes beside it instead
        out = out.with_suffix(".new.csv")
        print(f"{args.out} has other columns than these rows; writing them to {out}")
    table.to_csv(out, mode="a", header=not out.is_file(), index=False)
    models = {"cmvae": args.checkpoint} if args.tracker == "camera" else {}
    models |= {"detector": args.detector} if args.detector else {}
    write_provenance_beside(out, provenance(models, seeds=[args.seed], sim_config=args.sim_config or None), append=True)


if __name__ == "__main__":
    main()
