"""Who the rover follows in a pod, and whether that is the target: per-step ground truth and per-episode metrics.

The sim classifies every step from the dolphins' places in the camera's frame (:func:`followed_dolphin`,
:func:`target_occluded`) and reports both in the telemetry; the evaluator folds an episode's steps into its identity
metrics (:func:`episode_identity`). Dolphin 0 is the target, 1 on its companions, :data:`NONE` no dolphin.

Definitions (docs/physics.md, "Pods"; docs/eval_report.md, "Pods"):
- A dolphin is *in view* when its body centre is in front of the camera and inside the image.
- A dolphin is *hidden* when another is nearer the camera and their discs (a sphere of the body's girth round each
  centre) overlap as the camera sees them; the target hidden so is *occluded*.
- The rover *follows* the dolphin in view and not hidden whose centre is nearest the image centre, by angle off the
  camera's axis (a companion passing behind the target does not take its place). While the target is occluded, who
  is followed is undefined (the tracker may rightly hold on to where it went), so those steps are left out of the
  metrics below.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from services.geometry import ALPHA_DEG, BETA_DEG, CAMERA_ABOVE_M, camera_centred

TARGET, NONE = 0, -1
#: Half a dolphin's girth (the target box's width, 0.88 m): the sphere round a body centre that hides what is behind.
DOLPHIN_RADIUS_M = 0.44
#: An episode keeps identity when the rover follows the target on at least this share of its unoccluded steps.
KEPT_SHARE = 0.9
#: Per-episode identity columns of an evaluation's rows, in order.
IDENTITY_ROW_FIELDS = ("identity_share", "identity_kept", "switches", "occlusions", "reacquire_steps", "unrecovered")


def off_axis_deg(points: np.ndarray) -> np.ndarray:
    """Each point's angle off the camera's axis, degrees; ``points`` (N, 3) in the camera's (forward, left, up)."""
    points = np.asarray(points, dtype=float)
    cosine = points[:, 0] / np.maximum(np.linalg.norm(points, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def level_camera_points(rover: np.ndarray, rover_yaw_deg: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """World ``positions`` (N, K, 3) in the camera's (forward, left, up) frame of N level rovers at ``rover`` (N, 3)
    heading ``rover_yaw_deg`` (N,): a dataset's dolphins as the camera saw them (datasets place the rover level)."""
    rover = np.asarray(rover, dtype=float)[:, None, :]
    positions = np.asarray(positions, dtype=float)
    yaw = np.asarray(rover_yaw_deg, dtype=float)[:, None]
    distance, azimuth = camera_centred(rover[..., :2], yaw, positions[..., :2])
    up = positions[..., 2] - rover[..., 2] - CAMERA_ABOVE_M
    azimuth = np.radians(azimuth)
    return np.stack([distance * np.cos(azimuth), distance * np.sin(azimuth), up], axis=-1)


def in_view(points: np.ndarray) -> np.ndarray:
    """Whether each point (camera frame, (forward, left, up)) is in front of the camera and inside the image."""
    points = np.asarray(points, dtype=float)
    forward, left, up = points[:, 0], points[:, 1], points[:, 2]
    azimuth = np.degrees(np.arctan2(np.abs(left), forward))
    elevation = np.degrees(np.arctan2(np.abs(up), forward))
    return (forward > 0) & (azimuth <= ALPHA_DEG) & (elevation <= BETA_DEG)


def followed_dolphin(points: np.ndarray) -> int:
    """The dolphin (row of ``points``, camera frame) in view, not hidden, nearest the image centre, or :data:`NONE`."""
    angles = np.where(in_view(points) & ~hidden(points), off_axis_deg(points), np.inf)
    nearest = int(np.argmin(angles))
    return nearest if math.isfinite(angles[nearest]) else NONE


def target_occluded(points: np.ndarray) -> bool:
    """Whether a companion (rows 1 on of ``points``, camera frame) is nearer the camera and overlaps the target."""
    return bool(hidden(points)[TARGET])


def hidden(points: np.ndarray) -> np.ndarray:
    """Whether each dolphin (rows of ``points``, camera frame) has a nearer one overlapping it as the camera sees."""
    points = np.asarray(points, dtype=float)
    distances = np.maximum(np.linalg.norm(points, axis=1), 1e-12)
    directions = points / distances[:, None]
    apart = np.arccos(np.clip(directions @ directions.T, -1.0, 1.0))
    radius = _angular_radius(distances)
    nearer = distances[None, :] < distances[:, None]  # [i, j]: j is nearer the camera than i
    return np.any(nearer & (apart < radius[:, None] + radius[None, :]), axis=1)


def _angular_radius(distance: np.ndarray) -> np.ndarray:
    """The half-angle a dolphin's girth sphere spans at ``distance`` (a camera inside it sees it fill the view)."""
    return np.arcsin(np.clip(DOLPHIN_RADIUS_M / distance, 0.0, 1.0))


def episode_identity(followed: Sequence[int], occluded: Sequence[bool]) -> dict[str, float | int | bool]:
    """One episode's identity metrics from its steps' followed dolphin and target occlusion.

    - ``identity_share``: of the steps with the target not occluded, the share where the rover follows it (a target
      out of view counts as not followed); NaN when every step is occluded.
    - ``identity_kept``: ``identity_share`` >= :data:`KEPT_SHARE`.
    - ``switches``: changes of the followed dolphin, over the unoccluded steps that follow one (NONE gaps skipped).
    - ``occlusions``: runs of occluded steps that end before the episode does.
    - ``reacquire_steps``: mean over those occlusions of the steps from the first clear step to the first step the
      target is followed (0: followed at once); NaN when none was re-acquired.
    - ``unrecovered``: occlusions after which the target is never followed again.
    """
    if len(followed) != len(occluded) or len(followed) == 0:
        raise ValueError(f"need as many followed as occluded steps, at least one: got {len(followed)}, {len(occluded)}")
    clear = [who for who, hidden in zip(followed, occluded, strict=True) if not hidden]
    share = sum(who == TARGET for who in clear) / len(clear) if clear else math.nan
    seen = [who for who in clear if who != NONE]
    switches = sum(a != b for a, b in zip(seen, seen[1:], strict=False))
    delays = _reacquire_delays(followed, occluded)
    found = [delay for delay in delays if delay is not None]
    return {
        "identity_share": share,
        "identity_kept": share >= KEPT_SHARE,
        "switches": switches,
        "occlusions": len(delays),
        "reacquire_steps": sum(found) / len(found) if found else math.nan,
        "unrecovered": len(delays) - len(found),
    }


def _reacquire_delays(followed: Sequence[int], occluded: Sequence[bool]) -> list[int | None]:
    """For each occlusion that ends in the episode, the steps from its end to the target followed (None: never)."""
    delays: list[int | None] = []
    for step in range(1, len(occluded)):
        if occluded[step - 1] and not occluded[step]:
            delays.append(_steps_to_target(followed, occluded, step))
    return delays


def _steps_to_target(followed: Sequence[int], occluded: Sequence[bool], start: int) -> int | None:
    """Steps from ``start`` to the first unoccluded step following the target, if one comes."""
    for step in range(start, len(followed)):
        if followed[step] == TARGET and not occluded[step]:
            return step - start
    return None
