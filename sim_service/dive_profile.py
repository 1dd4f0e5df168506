"""The 3d dolphin's dive profile: its depth and climb angle over time for one seed, as docs/physics.md shows it.

    python -m sim_service.dive_profile --out docs/dolphin_3d.png --seed 7 --seconds 300

The rover holds still at its start; the dolphin swims the ``3d`` motion (sim_service/dolphin.py).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

from sim_service.dolphin import DolphinParams  # noqa: E402
from sim_service.settings import DolphinSettings, WorldSettings  # noqa: E402
from sim_service.world import World  # noqa: E402


def dive_profile(seed: int, seconds: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time (s), depth (m, + down) and climb angle (deg, + up) of the dolphin's body, one row per step."""
    world = World(WorldSettings(render=False, dolphin=DolphinSettings(motion="3d")))
    try:
        poses = [world.reset(seed)[0]]
        poses += [world.step((0, 0, 0, 0))[0] for _ in range(round(seconds / world.dt))]
        dt = world.dt
    finally:
        world.close()
    depth = np.array([-pose.target_pos[2] for pose in poses])
    climb = np.degrees([math.asin(pose.target_forward[2]) for pose in poses])
    return np.arange(len(poses)) * dt, depth, climb


def plot(seed: int, seconds: float, out: Path) -> Path:
    time, depth, climb = dive_profile(seed, seconds)
    params = DolphinParams()
    fig, (depth_axis, climb_axis) = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True, height_ratios=(2, 1))
    depth_axis.plot(time, depth, color="tab:blue")
    for edge in (-params.ceiling_z, -params.floor_z):
        depth_axis.axhline(edge, color="grey", linestyle="--", linewidth=0.8)
    depth_axis.set_ylim(-params.floor_z + 1, 0)
    depth_axis.set_ylabel("depth (m)")
    depth_axis.set_title(f"3d dolphin, seed {seed}: depth band {-params.ceiling_z:g} to {-params.floor_z:g} m")
    climb_axis.plot(time, climb, color="tab:orange")
    climb_axis.set_ylim(-params.max_climb_deg - 5, params.max_climb_deg + 5)
    climb_axis.set_ylabel("climb (deg)")
    climb_axis.set_xlabel("time (s)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/dolphin_3d.png"))
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--seconds", type=float, default=300.0)
    args = parser.parse_args()
    print(plot(args.seed, args.seconds, args.out))


if __name__ == "__main__":
    main()
