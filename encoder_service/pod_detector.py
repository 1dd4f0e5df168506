"""Every dolphin in a frame: a small centre-point detector for pods (issue 47's perception that keeps identity).

A CMVAE reads *the* dolphin, which a pod leaves undefined. The detector reads all of them: a heatmap of dolphin
centres on a coarse grid (one cell per ``stride`` pixels), with each cell's sub-cell offset and the log of
that dolphin's distance (CenterNet's recipe, Zhou et al. 2019, shrunk to 64x64 frames). Which detection is the
target is the tracker's business (services.pod_tracker), across frames.

Labels come from a pod dataset's stored poses (``swimm dataset --dolphin-pod-size N --masks``): every dolphin's
body centre projected by the pinhole camera; a dolphin counts as seen when its centre is in view and no nearer
one hides it (services.identity), the target also when its own mask still shows pixels of it. Dolphins in view
but hidden are left out of the heatmap's loss rather than taught as background.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from services.detections import TAN_ALPHA, TAN_BETA, Detections, read_peaks
from services.identity import hidden, in_view, level_camera_points

#: Heatmap peaks' spread in pixels: about the blur of a centre read to a pixel or two.
PEAK_SIGMA_PX = 2.4
#: A target mask with fewer pixels than this is a dolphin the frame does not show.
MIN_TARGET_PIXELS = 4


def to_pixels(points: np.ndarray, size: int) -> np.ndarray:
    """Camera-frame points (..., 3) as (forward, left, up) -> image (x, y) in pixels of a ``size`` square frame."""
    forward = np.maximum(points[..., 0], 1e-6)
    x = (1.0 - points[..., 1] / forward / TAN_ALPHA) * size / 2
    y = (1.0 - points[..., 2] / forward / TAN_BETA) * size / 2
    return np.stack([x, y], axis=-1)


def dolphin_points(poses: np.ndarray, companions: np.ndarray) -> np.ndarray:
    """A pod dataset's rows as (N, K, 3) camera-frame points, the target first (row 0), its companions after."""
    positions = np.concatenate([poses[:, None, 6:9], companions[..., :3]], axis=1)
    return level_camera_points(poses[:, :3], poses[:, 5], positions)


def seen_dolphins(points: np.ndarray, target_pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(seen, ignored) booleans (N, K): in view and unhidden (the target: also showing pixels), and in view but not
    seen, whose cells the heatmap loss skips."""
    seen = np.zeros(points.shape[:2], dtype=bool)
    ignored = np.zeros_like(seen)
    for row, frame in enumerate(points):
        visible = in_view(frame)
        clear = visible & ~hidden(frame)
        clear[0] = visible[0] and target_pixels[row] >= MIN_TARGET_PIXELS
        seen[row], ignored[row] = clear, visible & ~clear
    return seen, ignored


def heatmap_targets(
    pixels: np.ndarray, distances: np.ndarray, seen: np.ndarray, ignored: np.ndarray, size: int, stride: int
) -> dict[str, np.ndarray]:
    """Per-cell training targets for frames of dolphins at ``pixels`` (N, K, 2): the Gaussian peak map, a mask of
    cells the loss skips, and at each seen dolphin's cell its offset within the cell and its log distance."""
    n, grid = len(pixels), size // stride
    heat = np.zeros((n, grid, grid), np.float32)
    skip = np.zeros((n, grid, grid), bool)
    centre = np.zeros((n, grid, grid), bool)
    regress = np.zeros((n, 3, grid, grid), np.float32)  # offset x, offset y (cells), log distance
    cells = np.arange(grid) + 0.5
    for row, k in zip(*np.nonzero(seen | ignored), strict=True):
        cx, cy = pixels[row, k] / stride
        ix, iy = int(np.clip(cx, 0, grid - 1)), int(np.clip(cy, 0, grid - 1))
        if ignored[row, k]:
            skip[row, max(iy - 1, 0) : iy + 2, max(ix - 1, 0) : ix + 2] = True
            continue
        spread = 2 * (PEAK_SIGMA_PX / stride) ** 2
        peak = np.outer(np.exp(-((cells - cy) ** 2) / spread), np.exp(-((cells - cx) ** 2) / spread))
        heat[row] = np.maximum(heat[row], peak)
        heat[row, iy, ix] = 1.0
        centre[row, iy, ix] = True
        regress[row, :, iy, ix] = (cx - ix, cy - iy, math.log(distances[row, k]))
    return {"heat": heat, "skip": skip & (heat < 1.0), "centre": centre, "regress": regress}


def _block(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class PodDetector(nn.Module):
    """Frames (N, 3, 64, 64) in [-1, 1] (encoder_service.model.images_to_tensor) -> (heat logits (N, 1, G, G),
    regression (N, 3, G, G)), G = 64 / stride.

    Features at three scales: 8x8 (a dolphin 2 m away spans half the frame) for what and how far, 16x16 for where,
    and at stride 2 also 32x32, so that two dolphins a few pixels apart keep a peak each.
    """

    def __init__(self, width: int = 16, stride: int = 4) -> None:
        super().__init__()
        if stride not in (2, 4):
            raise ValueError(f"the detector's stride is 2 or 4 pixels a cell, got {stride}")
        self.width, self.stride = width, stride
        self.stem = _block(3, width, 2)
        self.fine = nn.Sequential(_block(width, 2 * width, 2), _block(2 * width, 2 * width))
        self.coarse = nn.Sequential(
            _block(2 * width, 4 * width, 2), _block(4 * width, 4 * width), _block(4 * width, 4 * width, dilation=2)
        )
        self.join = _block(6 * width, 2 * width)
        self.sharpen = _block(3 * width, width) if stride == 2 else None
        out = width if stride == 2 else 2 * width
        self.heat = nn.Conv2d(out, 1, 1)
        self.regress = nn.Conv2d(out, 3, 1)
        nn.init.constant_(self.heat.bias, -2.2)  # CenterNet's start: most cells are background

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # Each frame evened per channel: the water's colour and brightness say nothing of where a dolphin is.
        mean = images.mean(dim=(2, 3), keepdim=True)
        std = images.std(dim=(2, 3), keepdim=True) + 0.04
        stem = self.stem((images - mean) / std)
        fine = self.fine(stem)
        coarse = F.interpolate(self.coarse(fine), size=fine.shape[-2:], mode="nearest")
        joined = self.join(torch.cat([fine, coarse], dim=1))
        if self.sharpen is not None:
            joined = self.sharpen(torch.cat([stem, F.interpolate(joined, size=stem.shape[-2:], mode="nearest")], 1))
        return self.heat(joined), self.regress(joined)


def focal_loss(logits: torch.Tensor, heat: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss over the cells not skipped, per dolphin."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    peak = heat >= 1.0
    positive = -((1 - p) ** 2) * torch.log(p) * peak
    negative = -((1 - heat) ** 4) * p**2 * torch.log(1 - p) * (~peak & ~skip)
    return (positive.sum() + negative.sum()) / peak.sum().clamp(min=1)


def detector_loss(heat_logits, regression, targets: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
    """Focal heatmap loss plus L1 on offsets and log distances at the dolphins' cells."""
    heat_loss = focal_loss(heat_logits[:, 0], targets["heat"], targets["skip"])
    centre = targets["centre"][:, None].expand_as(regression)
    count = targets["centre"].sum().clamp(min=1)
    error = (regression - targets["regress"]).abs() * centre
    offset_loss = error[:, :2].sum() / count
    distance_loss = error[:, 2].sum() / count
    total = heat_loss + offset_loss + 5.0 * distance_loss
    return total, {"heat": heat_loss.item(), "offset": offset_loss.item(), "log_d": distance_loss.item()}


def decode(
    heat_logits: torch.Tensor,
    regression: torch.Tensor,
    threshold: float,
    size: int,
    stride: int,
    images: np.ndarray | None = None,
) -> list[Detections]:
    """Peaks above ``threshold`` (3x3 local maxima of the sigmoid heat) as each frame's :class:`Detections`, with
    their looks where the frames are given."""
    heat = torch.sigmoid(heat_logits[:, 0]).detach().cpu().numpy()
    return read_peaks(heat, regression.detach().cpu().numpy(), threshold, size, stride, images)
