"""The rover camera's viewing frustum and whether the target's bounding box is inside it.

The frustum comes from the physical camera in the MJCF (IMX322: 2.97 mm
focal length, 4.98 x 3.74 mm sensor), the same numbers MuJoCo renders with.
"In view" means the target's oriented bounding box and the frustum overlap
(some part of the dolphin can be on screen): the target is lost only when
its whole bounding volume has left, as in the reference simulator.

The overlap test is exact: the separating-axis theorem for two convex
polyhedra (the box and the truncated pyramid between the near and far
planes), whose candidate axes are both shapes' face normals and the cross
products of their edge directions.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from itertools import product

import mujoco
import numpy as np


@dataclass(frozen=True)
class CameraFrustum:
    tan_half_width: float  # tan of half the horizontal field of view
    tan_half_height: float
    near: float  # m
    far: float  # m

    @classmethod
    def from_model(cls, model: mujoco.MjModel, camera_id: int) -> CameraFrustum:
        focal = model.cam_intrinsic[camera_id][:2]
        sensor = model.cam_sensorsize[camera_id]
        extent = model.stat.extent
        return cls(
            tan_half_width=float(sensor[0] / (2 * focal[0])),
            tan_half_height=float(sensor[1] / (2 * focal[1])),
            near=float(model.vis.map.znear * extent),
            far=float(model.vis.map.zfar * extent),
        )

    def corners_camera(self) -> np.ndarray:
        """The 8 corners in the camera frame (x right, y up, looking along -z): near 4 then far 4."""
        signs = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], dtype=float)
        corners = []
        for depth in (self.near, self.far):
            for sx, sy in signs:
                corners.append((sx * depth * self.tan_half_width, sy * depth * self.tan_half_height, -depth))
        return np.array(corners)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Normalised image coordinates in [-1, 1]^2 on screen (x right, y up) of camera-frame points."""
        depth = -points_camera[:, 2:3]
        scale = np.array([self.tan_half_width, self.tan_half_height])
        return points_camera[:, :2] / (depth * scale)

    def sees_box(
        self,
        camera_pos: np.ndarray,
        camera_rot: np.ndarray,
        box_centre: np.ndarray,
        box_rot: np.ndarray,
        box_size: tuple[float, float, float],
    ) -> bool:
        """True when the box (centre, body-to-world rotation, full edge lengths) overlaps the frustum.

        Works in the camera frame, where the frustum's corners, edges and face normals are constants.
        """
        camera_rot = np.asarray(camera_rot)
        centre = camera_rot.T @ (np.asarray(box_centre) - np.asarray(camera_pos))
        half = np.asarray(box_size, dtype=float) / 2
        # Quick answers from the bounding sphere; the exact test below runs only near the frustum's edges.
        plane_distances = self._unit_normals @ centre - self._offsets
        radius = float(np.sqrt(half @ half))
        if plane_distances.max() > radius:
            return False
        if plane_distances.max() < -radius:
            return True
        box_axes = camera_rot.T @ np.asarray(box_rot)  # columns: the box's axes in the camera frame
        half_extents = box_axes * half
        box_corners = centre + _BOX_SIGNS @ half_extents.T
        crosses = np.cross(box_axes.T[:, None, :], self._edges[None, :, :]).reshape(-1, 3)
        axes = np.concatenate([box_axes.T, self._normals, crosses])
        axes = axes[np.einsum("ij,ij->i", axes, axes) > 1e-12]
        box_proj = box_corners @ axes.T
        frustum_proj = self._corners @ axes.T
        box_before = box_proj.max(axis=0) < frustum_proj.min(axis=0)
        box_after = frustum_proj.max(axis=0) < box_proj.min(axis=0)
        return not bool((box_before | box_after).any())

    @cached_property
    def _corners(self) -> np.ndarray:
        return self.corners_camera()

    @cached_property
    def _edges(self) -> np.ndarray:
        """Edge directions: the rims' x and y, and the four side edges from near to far corners."""
        c = self._corners
        return np.array([[1.0, 0, 0], [0, 1.0, 0]] + [c[i + 4] - c[i] for i in range(4)])

    @cached_property
    def _normals(self) -> np.ndarray:
        """Face normals: near/far planes (z) and each side plane, spanned by a side edge and a rim edge."""
        c = self._corners
        sides = [np.cross(c[i + 4] - c[i], c[(i + 1) % 4] - c[i]) for i in range(4)]
        return np.array([[0, 0, 1.0], *sides])

    @cached_property
    def _unit_normals(self) -> np.ndarray:
        """Outward unit normals of the near plane and the four side planes (far plane ignored: 60 m)."""
        c = self._corners
        sides = [np.cross(c[i + 4] - c[i], c[(i + 1) % 4] - c[i]) for i in range(4)]
        normals = np.array([[0, 0, 1.0], *sides])
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)

    @cached_property
    def _offsets(self) -> np.ndarray:
        """Signed plane offsets: distance(p) = normal . p - offset, positive outside."""
        return np.array([-self.near, 0, 0, 0, 0])


_BOX_SIGNS = np.array(list(product((-1.0, 1.0), repeat=3)))
