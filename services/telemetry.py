"""Ground-truth state of one environment at one step.

The sim fills a :class:`Telemetry` every step; the learner's task derives
reward and termination from it and the evaluator its metrics. It is plain
data (tuples of floats) so that it crosses msgpack unchanged and compares
bit-for-bit between in-process and distributed runs.

Frames: MuJoCo world frame, z up, metres, radians for angular rates.
Quaternions are (w, x, y, z) as MuJoCo stores them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


@dataclass(frozen=True)
class Telemetry:
    rover_pos: Vec3
    rover_quat: Quat
    rover_forward: Vec3
    rover_lin_vel: Vec3  # world frame, m/s
    rover_ang_vel: Vec3  # world frame, rad/s
    target_pos: Vec3
    target_quat: Quat
    target_forward: Vec3
    target_lin_vel: Vec3
    target_in_frustum: bool  # target's bounding volume wholly inside the camera frustum
    collided: bool  # rover and target bodies in contact this step
    sim_time: float  # seconds since reset
    # A pod's identity ground truth (services/identity.py); a single dolphin's are its own: followed when in view.
    pod_size: int = 1  # dolphins in the world, the target included
    followed: int = 0  # the dolphin in view nearest the image centre: 0 the target, 1 on companions, -1 none
    target_occluded: bool = False  # a companion between the camera and the target hides it

    def __deepcopy__(self, memo: dict) -> Telemetry:
        """Immutable (frozen, tuples of floats): a copy is the object itself. SB3's VecEnvs deep-copy infos
        every step, and the generic deepcopy of this dataclass cost more than a whole physics step."""
        return self

    def to_dict(self) -> dict[str, Any]:
        # Field by field: dataclasses.asdict deep-copies recursively, about 25x slower, and this runs on every message.
        return {name: list(getattr(self, name)) if size > 1 else getattr(self, name) for name, size in _SCHEMA}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Telemetry:
        """Rebuild from a decoded message; raises ValueError on a missing or malformed field."""
        values: dict[str, Any] = {}
        for name, size in _SCHEMA:
            if name not in data:
                raise ValueError(f"telemetry lacks field {name!r}")
            raw = data[name]
            if size == 0:
                values[name] = raw if type(raw) is bool else bool(raw)
            elif size == INTEGER:
                values[name] = _integer(name, raw)
            elif size == 1:
                values[name] = float(raw)
            elif isinstance(raw, (list, tuple)) and len(raw) == size:
                values[name] = tuple(map(float, raw))
            else:
                raise ValueError(f"telemetry field {name!r} must have {size} numbers")
        return cls(**values)

    @classmethod
    def unknown(cls, sim_time: float) -> Telemetry:
        """What a real camera's frame carries (`swimm pilot --publish`): no ground truth, so every position,
        orientation and velocity NaN, neither flag set and no dolphin followed; only the seconds since the session
        began."""
        nan = float("nan")
        measured = {name: (False if size == 0 else nan if size == 1 else (nan,) * size)
                    for name, size in _SCHEMA if size != INTEGER}  # fmt: skip
        return cls(**measured | {"sim_time": float(sim_time), "pod_size": 1, "followed": -1})


def _integer(name: str, raw: Any) -> int:
    if type(raw) is not int:
        raise ValueError(f"telemetry field {name!r} must be an integer")
    return raw


#: (field name, how many numbers: 0 a bool, 1 a float, 3 a vector, 4 a quaternion, INTEGER an int), worked out
#: once: looking the dataclass fields up on every message cost more than decoding them.
INTEGER = -1
_SIZES = {"bool": 0, "int": INTEGER, "float": 1, "Vec3": 3, "Quat": 4}
_SCHEMA = tuple((f.name, _SIZES[f.type]) for f in fields(Telemetry))
