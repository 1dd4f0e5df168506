"""Photometric jitter of training frames: colours, light and sensor effects drawn with no water model behind them.

The sim's noise draws water from a handful of natural colours and strengths up to the harsh preset; real water is
any colour and any light. Jittering the encoder's input in image space (as DMControl-GB's strongest methods do
with colour jitter and random convolutions) teaches it that the dolphin's outline, not the water's look, says
where the dolphin is. The targets stay the clean twin's, so the latent learns to ignore the jitter. Ranges are
data here; docs/encoder.md says why each is as wide as it is, and the held-out splits stay outside the sim's
training settings (sim_service/splits.py), which this jitter does not set.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

GAIN_LOG_RANGE = 0.8  # per-channel gain exp(U[-r, r]): about 0.45x to 2.2x
OFFSET_RANGE = 40.0  # per-channel offset U[-r, r], 0-255 units
GAMMA_LOG_RANGE = 0.5  # gamma exp(U[-r, r]): about 0.6 to 1.65
HAZE_MAX = 0.5  # blend toward a random colour by U[0, max]: backscatter of any water
NOISE_STD_MAX = 12.0  # Gaussian pixel noise, std U[0, max]
BLUR_SIGMA_MAX = 1.2  # Gaussian blur, sigma U[0, max] pixels, on half of the jittered frames
BANDS_MAX = 4  # translucent bands per banded frame, 1 to max
BAND_WIDTH = (0.03, 0.5)  # band width where it crosses its centre, a share of the frame's width U[lo, hi]
BAND_SPREAD_MAX = 3.0  # a band widens by up to this many times its width per frame width along it: a wedge
BAND_ALPHA_MAX = 0.5  # a band's peak opacity U[0.1, max]: the dolphin still shows through
SHAFTS = (2, 6)  # light shafts per frame with shafts, U{lo..hi}
SHAFT_SPREAD_DEG = 6.0  # a shaft's direction within this many degrees of the set's
SHAFT_LIGHT = (150.0, 255.0)  # the shafts' grey level U[lo, hi], 0-255 units: sunlight is pale
SHAFT_TINT = 20.0  # per-channel tint U[-t, t] on that grey
FAN_RAYS = (3, 7)  # rays per fanned frame, U{lo..hi}
FAN_RAY_HALF_DEG = (0.7, 4.0)  # a ray's angular half width seen from its vanishing point, U[lo, hi] degrees
FAN_ALPHA = (0.2, 0.5)  # a ray's opacity U[lo, hi]
DEFOCUS_SIGMA = (0.5, 3.0)  # --augment-blur: Gaussian blur, sigma U[lo, hi] pixels
CONTRAST_LOG_RANGE = 0.9  # the dolphin's contrast to its water times exp(U[-r, r]): about 0.4x to 2.5x
CONTRAST_FLIP_SHARE = 0.3  # of those, this share also turned around: a dark dolphin on a pale, bright water
WATER_SIGMA_PX = 4.0  # the water behind the dolphin: its surroundings blurred over this many pixels


@dataclass
class AugmentSettings:
    """The trainers' image jitter: the share of training frames each change is drawn on (0: off)."""

    augment: float = 0.0  # share of training frames fed with a random photometric jitter (encoder_service.augment)
    augment_bands: float = 0.0  # share of training frames crossed by translucent bands (encoder_service.augment)
    augment_shafts: float = 0.0  # share of training frames crossed by a sun's pale, near-parallel light shafts
    augment_blur: float = 0.0  # share of training frames blurred as by a camera out of focus (encoder_service.augment)
    augment_fans: float = 0.0  # share of training frames crossed by shafts seen in perspective: rays from one point

    def check_shares(self) -> None:
        """Refuse a share outside [0, 1], naming its flag."""
        shares = (("--augment", self.augment), ("--augment-bands", self.augment_bands),
                  ("--augment-shafts", self.augment_shafts), ("--augment-blur", self.augment_blur),
                  ("--augment-fans", self.augment_fans))  # fmt: skip
        for flag, share in shares:
            check_share(flag, share)

    def augmented(self, images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Frames through :func:`jitter`, :func:`bands`, :func:`shafts`, :func:`fans` and :func:`defocus` in turn,
        each on its share of them (``images`` itself when all are off)."""
        changes = ((jitter, self.augment), (bands, self.augment_bands), (shafts, self.augment_shafts),
                   (fans, self.augment_fans), (defocus, self.augment_blur))  # fmt: skip
        for change, share in changes:
            if share > 0:
                images = change(images, rng, share)
        return images


def check_share(flag: str, share: float) -> None:
    """Refuse an augmentation share outside [0, 1], naming its flag."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"{flag} is a share of frames: it must lie in [0, 1], got {share}")


def jitter(images: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which a ``share`` of them carry a random photometric jitter."""
    return _on_share(images, rng, share, _jitter_one)


def _on_share(
    images: np.ndarray,
    rng: np.random.Generator,
    share: float,
    change: Callable[[np.ndarray, np.random.Generator], np.ndarray],
) -> np.ndarray:
    """A copy of ``images`` in which a random ``share`` of them went through ``change``."""
    out = images.copy()
    for index in np.flatnonzero(rng.random(len(images)) < share):
        out[index] = change(images[index], rng)
    return out


def _jitter_one(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    pixels = image.astype(np.float32) / 255.0
    pixels = np.clip(pixels, 0.0, 1.0) ** np.exp(rng.uniform(-GAMMA_LOG_RANGE, GAMMA_LOG_RANGE))
    pixels = pixels * np.exp(rng.uniform(-GAIN_LOG_RANGE, GAIN_LOG_RANGE, 3)) + rng.uniform(-1, 1, 3) * (
        OFFSET_RANGE / 255.0
    )
    haze = rng.uniform(0.0, HAZE_MAX)
    pixels = (1.0 - haze) * pixels + haze * rng.uniform(0.0, 1.0, 3)
    if rng.random() < 0.5:
        pixels = cv2.GaussianBlur(pixels, (0, 0), rng.uniform(1e-3, BLUR_SIGMA_MAX))
    pixels += rng.standard_normal(pixels.shape, dtype=np.float32) * (rng.uniform(0.0, NOISE_STD_MAX) / 255.0)
    return np.rint(np.clip(pixels, 0.0, 1.0) * 255.0).astype(np.uint8)


def bands(images: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which a ``share`` of them carry translucent straight bands.

    Each band crosses the frame at any angle in a random colour, fades along its length and may widen along it
    into a wedge, as light shafts under a low sun, kelp or a passing shadow would: structure that is not the
    dolphin and that the sim's training scenery draws only in a narrow range of angles, widths and strengths.
    """
    return _on_share(images, rng, share, _bands_one)


def _bands_one(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return _banded(image, rng, rng.integers(1, BANDS_MAX + 1), lambda: rng.uniform(0.0, np.pi))


def shafts(images: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which a ``share`` of them carry a sun's light shafts.

    Sunlight through a wavy surface falls in pale bands that run nearly parallel, many at once, the lower the sun
    the more slanted: :func:`bands` drawn as one such set (one pale colour, one direction give or take a few
    degrees), a structure in the frame that is light, not the dolphin.
    """
    return _on_share(images, rng, share, _shafts_one)


def _shafts_one(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    direction = rng.uniform(0.0, np.pi)
    colour = _sunlight(rng)
    count = rng.integers(SHAFTS[0], SHAFTS[1] + 1)

    def near_direction() -> float:
        return direction + np.deg2rad(rng.uniform(-SHAFT_SPREAD_DEG, SHAFT_SPREAD_DEG))

    return _banded(image, rng, count, near_direction, colour)


def _sunlight(rng: np.random.Generator) -> np.ndarray:
    """A pale, slightly tinted grey: the colour of one sun's shafts."""
    return np.clip(rng.uniform(*SHAFT_LIGHT) + rng.uniform(-SHAFT_TINT, SHAFT_TINT, 3), 0.0, 255.0).astype(np.float32)


def fans(images: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which a ``share`` of them carry a low sun's shafts in perspective.

    Shafts are parallel in the water, so the camera sees them converge on one vanishing point, which a low sun
    brings near or into the frame: pale rays fanning out from one point in or around it, crossing the frame
    wherever the dolphin is. :func:`shafts` draws them parallel, as a high sun's look.
    """
    return _on_share(images, rng, share, _fan_one)


def _fan_one(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    height, width = image.shape[:2]
    return fan_from(image, rng, (rng.uniform(-width, 2 * width), rng.uniform(-1.5 * height, 2.5 * height)))


def fan_from(image: np.ndarray, rng: np.random.Generator, point: tuple[float, float]) -> np.ndarray:
    """``image`` (uint8) crossed by pale rays from the vanishing ``point`` (x, y in pixels)."""
    height, width = image.shape[:2]
    point_x, point_y = point
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    bearing = np.arctan2(rows - point_y, cols - point_x)
    reach = np.hypot(rows - point_y, cols - point_x)
    to_centre = np.arctan2(height / 2 - point_y, width / 2 - point_x)
    # rays aimed about as wide as the frame spans from the point, or anywhere when the point lies inside it
    inside_frame = 0 <= point_x < width and 0 <= point_y < height
    spread = np.pi if inside_frame else np.arctan2(width, np.hypot(height / 2 - point_y, width / 2 - point_x))
    colour = _sunlight(rng)
    pixels = image.astype(np.float32)
    for _ in range(rng.integers(FAN_RAYS[0], FAN_RAYS[1] + 1)):
        off_ray = np.angle(np.exp(1j * (bearing - to_centre - rng.uniform(-spread, spread))))  # wrapped to (-pi, pi]
        half_width = np.deg2rad(rng.uniform(*FAN_RAY_HALF_DEG))
        inside = np.clip((half_width - np.abs(off_ray)) * reach + 0.5, 0.0, 1.0)  # a one-pixel soft edge
        alpha = (rng.uniform(*FAN_ALPHA) * inside)[..., None]
        pixels = pixels * (1.0 - alpha) + colour * alpha
    return np.rint(np.clip(pixels, 0.0, 255.0)).astype(np.uint8)


def _banded(
    image: np.ndarray,
    rng: np.random.Generator,
    count: int,
    angle: Callable[[], float],
    colour: np.ndarray | None = None,
) -> np.ndarray:
    """``image`` crossed by ``count`` bands, each at an ``angle()`` drawn just before it, in ``colour`` (a random
    one per band if None)."""
    rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]].astype(np.float32)
    pixels = image.astype(np.float32)
    for _ in range(count):
        pixels = _band(pixels, rows, cols, rng, angle(), colour)
    return np.rint(np.clip(pixels, 0.0, 255.0)).astype(np.uint8)


def _band(
    pixels: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    rng: np.random.Generator,
    angle: float,
    colour: np.ndarray | None = None,
) -> np.ndarray:
    """``pixels`` (float, H x W x 3) with one translucent band across them at ``angle``, in ``colour`` (a random
    one if None)."""
    width = pixels.shape[1]
    centre_x, centre_y = rng.uniform(0, width), rng.uniform(0, pixels.shape[0])
    across = (cols - centre_x) * np.sin(angle) - (rows - centre_y) * np.cos(angle)
    along = ((cols - centre_x) * np.cos(angle) + (rows - centre_y) * np.sin(angle)) / width
    half_width = rng.uniform(*BAND_WIDTH) * width / 2 * np.clip(1.0 + rng.uniform(0, BAND_SPREAD_MAX) * along, 0, None)
    inside = np.clip(half_width - np.abs(across) + 0.5, 0.0, 1.0)  # a one-pixel soft edge
    fade = np.clip(0.5 + rng.uniform(-1.5, 1.5) * along, 0.0, 1.0)
    alpha = (rng.uniform(0.1, BAND_ALPHA_MAX) * inside * fade)[..., None]
    if colour is None:
        colour = rng.uniform(0.0, 255.0, 3).astype(np.float32)
    return pixels * (1.0 - alpha) + colour * alpha


def defocus(images: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which a ``share`` of them are blurred, sigma :data:`DEFOCUS_SIGMA`.

    Blur swells a small dolphin's blob, and a detector that reads distance off the blob's size then reads a far
    dolphin near (docs/encoder.md); the jitter's own blur stops at :data:`BLUR_SIGMA_MAX`.
    """
    return _on_share(
        images, rng, share, lambda image, rng: cv2.GaussianBlur(image, (0, 0), rng.uniform(*DEFOCUS_SIGMA))
    )


def contrast(images: np.ndarray, masks: np.ndarray, rng: np.random.Generator, share: float) -> np.ndarray:
    """A copy of uint8 frames (N, H, W, 3) in which, on a ``share`` of them, the dolphin's pixels (``masks``, N x H
    x W) stand out from the water behind them more or less than rendered, and on some of them the other way round
    (darker than the water where it was lighter, or the reverse); ``images`` itself at share 0, drawing nothing.

    A far dolphin fades into its water, and in a pale, bright water shows darker than it: scaling and turning its
    contrast at random, its size unchanged, keeps neither from standing in for distance (docs/encoder.md measures
    what it does to the read).
    """
    if share <= 0:
        return images
    out = images.copy()
    for index in np.flatnonzero(rng.random(len(images)) < share):
        if masks[index].any():
            out[index] = _contrast_one(images[index], masks[index], rng)
    return out


def _contrast_one(image: np.ndarray, mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    pixels = image.astype(np.float32)
    body = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 0.7)[..., None]  # soft edges, no seam
    around = 1.0 - cv2.dilate(mask.astype(np.float32), np.ones((3, 3), np.float32))[..., None]  # water alone
    mean_water = (pixels * around).sum(axis=(0, 1)) / max(float(around.sum()), 1.0)
    # The surroundings' colour, leaning on the frame's mean water deep inside a dolphin that fills the blur.
    water = (cv2.GaussianBlur(pixels * around, (0, 0), WATER_SIGMA_PX) + 0.01 * mean_water) / (
        cv2.GaussianBlur(around[..., 0], (0, 0), WATER_SIGMA_PX)[..., None] + 0.01
    )
    gain = np.exp(rng.uniform(-CONTRAST_LOG_RANGE, CONTRAST_LOG_RANGE))
    if rng.random() < CONTRAST_FLIP_SHARE:
        gain = -gain
    pixels += body * (gain - 1.0) * (pixels - water)
    return np.rint(np.clip(pixels, 0.0, 255.0)).astype(np.uint8)
