"""Image noise for the underwater camera: the paper's robustness study (fog, depth of field, motion blur,
barrel distortion, film grain), each a setting and all off by default.

Why a separate stage after rendering: the renderer draws a clean pinhole image; what the encoder sees
on a real BlueROV2 is degraded by the water and the optics. Keeping the degradations here, as a pure
function of (image, depth, rng, motion), lets datasets and training episodes switch noise on or off
without touching the world, and keeps noisy runs reproducible (every random draw comes from the
caller's ``np.random.Generator``).

Effects run in the order light meets them on its way to the sensor:

1. water (``attenuation``): the underwater image-formation model (as in OceanSim and the Jerlov water
   types): each colour channel decays with distance at its own rate, ``J exp(-beta_c z)``, and backscatter
   fills in toward the water colour, ``B_c (1 - exp(-beta_c z))``; red goes first in clear water;
2. fog: water scatters and absorbs light along the line of sight, so each pixel is blended toward the
   water colour by its depth (visibility ``exp(-(density * depth)^2)``, squared-exponential as in the SPEC);
3. marine snow: bright particles drifting between the camera and the scene, a Poisson count per frame;
4. depth of field: the lens focuses at ``focus_m``; the blur radius grows with the thin-lens circle of
   confusion, proportional to ``|depth - focus| / depth`` and capped at ``depth_of_field`` pixels;
5. motion blur: the scene moves across the sensor during the exposure, a line kernel along the apparent
   image motion, ``motion_blur`` pixels of smear per pixel of motion;
6. barrel distortion: the wide-angle lens bends rays, radius scaled by ``1 + k1 r^2`` (r = 1 at the middle
   of the longer image edge; samples beyond the frame are mirrored back in);
7. sensor noise: shot noise (per channel, std growing with the square root of the signal), then film grain
   (monochrome Gaussian with std ``grain``, 0-255 units);
8. JPEG compression at ``jpeg_quality``, as a camera's encoder leaves it.

Intermediate results stay float32 so effects do not quantise each other; the result is rounded once (JPEG
then codes the rounded frame). Each effect's cost per frame is measured in docs/physics.md.

Randomisation (``randomise``) is a training aid: each episode (or dataset sample) draws every effect's
strength from zero to its setting and the water colour from a range of natural water colours, all from the
episode's noise generator (:func:`draw_episode_noise`). What is evaluated are fixed settings, such as the
named presets (:data:`PRESETS`) or a preset scaled by a severity (:func:`scaled`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.settings import from_message

_MAX_DOF_LEVELS = 4  # blur levels (besides the sharp image) that depth of field interpolates between
_MIN_MOTION_PX = 1e-3  # smear shorter than this is no blur at all
_KERNEL_SUPERSAMPLING = 8  # motion-blur kernels are drawn at this many sub-pixels per pixel
_FIXED_POINT_BITS = 4  # sub-pixel precision of the drawn segment's end points


@dataclass
class NoiseSettings:
    """Image noise switches; simple field types so `services.settings` turns them into ``--noise-*`` flags."""

    preset: str = "off"  # off | murky | harsh: a named set of effects; effects set here that are above 0 win
    randomise: bool = False  # each episode draws every effect from 0 to its strength and a natural water colour
    clean_share: float = 0.0  # randomised: the share of episodes drawn with no noise at all (clean and noisy mixed)
    attenuation: float = 0.0  # per metre: each channel decays as exp(-attenuation * attenuation_rgb[c] * depth)
    attenuation_rgb: list[float] = field(default_factory=lambda: [1.0, 0.45, 0.3])  # relative R, G, B decay rates
    fog: float = 0.0  # density per metre: visibility exp(-(fog * depth)^2)
    fog_color: list[int] = field(default_factory=lambda: [20, 70, 90])  # RGB of the water fog and backscatter fade to
    marine_snow: float = 0.0  # mean number of particles per frame
    grain: float = 0.0  # std of film grain, 0-255 units
    shot_noise: float = 0.0  # std of shot noise at full brightness, 0-255 units (std grows as sqrt(signal))
    depth_of_field: float = 0.0  # largest blur radius in pixels, reached far from the focus distance
    focus_m: float = 6.0  # in-focus distance in metres (the tracking distance opt_d)
    distortion: float = 0.0  # barrel distortion coefficient k1
    motion_blur: float = 0.0  # pixels of smear per pixel of apparent image motion
    jpeg_quality: int = 0  # JPEG-compress each frame at this quality (1-100); 0 = off

    @property
    def enabled(self) -> bool:
        """True when at least one effect would change an image."""
        return any(getattr(self, name) > 0 for name in EFFECTS)

    @property
    def needs_depth(self) -> bool:
        """True when `ImageNoise.apply` needs a depth map (so the renderer knows to produce one)."""
        return self.fog > 0 or self.depth_of_field > 0 or self.attenuation > 0

    @classmethod
    def from_mapping(cls, values: dict) -> NoiseSettings:
        """Settings from a message's map (a reset's ``noise``), refusing unknown keys and wrong types by name."""
        settings = from_message(cls, values, "noise")
        ImageNoise(settings)  # validates ranges and the preset
        return settings

    def resolved(self) -> NoiseSettings:
        """These settings with the preset's effects filled in where this leaves an effect at 0."""
        if self.preset not in PRESETS:
            raise ValueError(f"unknown noise preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        base = PRESETS[self.preset]
        filled = {name: getattr(self, name) or getattr(base, name) for name in EFFECTS}
        return dataclasses.replace(self, preset="off", **filled)


def describe_noise(settings: NoiseSettings) -> str:
    """One line for logs: the preset, randomisation and every effect that is on."""
    resolved = settings.resolved()
    if not resolved.enabled:
        return "off"
    effects = ", ".join(f"{name} {getattr(resolved, name):g}" for name in EFFECTS if getattr(resolved, name) > 0)
    if settings.randomise:
        effects = f"randomised up to ({effects}), {settings.clean_share:.0%} of episodes clean"
    return effects if settings.preset == "off" else f"{settings.preset}: {effects}"


def noise_option(value: object) -> bool | NoiseSettings | None:
    """A reset's ``noise`` option as `World.reset` takes it: on/off, settings from a map, or None (unchanged)."""
    if isinstance(value, dict):
        return NoiseSettings.from_mapping(value)
    if value is None or isinstance(value, (bool, NoiseSettings)):
        return value
    raise ValueError(f"'noise' must be true, false, a map of noise settings or absent, got {value!r}")


#: The effects' strength fields: 0 is off, more is stronger (for JPEG, the quality: lower is stronger).
EFFECTS = (
    "attenuation", "fog", "marine_snow", "depth_of_field", "motion_blur", "distortion", "shot_noise", "grain",
    "jpeg_quality",
)  # fmt: skip

#: Named presets. ``murky`` is the one `--noise on` has always meant: a murky harbour at the tracking distance
#: (the target fades to about half contrast at 6 m), a slightly soft lens, visible grain. ``harsh`` adds coloured
#: water, marine snow, shot noise and JPEG, and strengthens the rest: the training range's upper end.
PRESETS = {
    "off": NoiseSettings(),
    "murky": NoiseSettings(fog=0.12, grain=6.0, depth_of_field=1.5, distortion=0.15, motion_blur=1.0),
    "harsh": NoiseSettings(
        attenuation=0.12, fog=0.15, marine_snow=12.0, grain=9.0, shot_noise=12.0, depth_of_field=2.5,
        distortion=0.25, motion_blur=1.5, jpeg_quality=40,
    ),
}  # fmt: skip
NOISY_PRESET = PRESETS["murky"]

#: Natural water colours (RGB of deep water seen horizontally): clear ocean blue, coastal blue-green, green
#: coastal, turbid green-brown. A randomised episode's water is a random mix of two neighbours.
WATER_COLOURS = ((10, 50, 100), (20, 70, 90), (30, 85, 70), (55, 75, 50))
_JPEG_BEST = 100


def scaled(settings: NoiseSettings, severity: float, effects: tuple[str, ...] = EFFECTS) -> NoiseSettings:
    """``settings`` with the named effects' strengths times ``severity`` and every other effect off.

    JPEG's quality moves from 100 toward the setting's: severity 1 is the setting, 2 twice as far from 100.
    The sweep of `swimm eval --sweep` plays policies on these.
    """
    if severity < 0:
        raise ValueError(f"noise severity must be >= 0, got {severity}")
    unknown = set(effects) - set(EFFECTS)
    if unknown:
        raise ValueError(f"unknown noise effects {sorted(unknown)}; choose from {', '.join(EFFECTS)}")
    values = {name: 0 for name in EFFECTS}
    for name in effects:
        value = getattr(settings, name)
        if name == "jpeg_quality":
            off = value <= 0 or severity == 0
            values[name] = 0 if off else max(1, round(_JPEG_BEST - severity * (_JPEG_BEST - value)))
        else:
            values[name] = value * severity
    return dataclasses.replace(settings, preset="off", randomise=False, **values)


def draw_episode_noise(settings: NoiseSettings, rng: np.random.Generator) -> NoiseSettings:
    """One episode's fixed settings drawn from ``settings`` read as maxima (see ``randomise``).

    Every effect's strength is uniform between 0 and its setting (JPEG's quality between the setting and 100), and
    the water colour a uniform mix of two neighbouring natural water colours; a ``clean_share`` of draws switch
    every effect off. The same generator state gives the same draw, so an episode's noise is fixed by its seed.
    """
    clean = rng.uniform(0.0, 1.0) < settings.clean_share
    values: dict[str, float | int] = {}
    for name in EFFECTS:
        value = getattr(settings, name)
        fraction = rng.uniform(0.0, 1.0)  # drawn for every effect, so one effect's setting never shifts another's draw
        if name == "jpeg_quality":
            values[name] = 0 if value <= 0 else round(value + fraction * (_JPEG_BEST - value))
        else:
            values[name] = value * fraction
    pick = int(rng.integers(len(WATER_COLOURS) - 1))
    mix = rng.uniform(0.0, 1.0)
    colour = (1 - mix) * np.asarray(WATER_COLOURS[pick]) + mix * np.asarray(WATER_COLOURS[pick + 1])
    if clean:
        values = {name: 0 for name in EFFECTS}
    return dataclasses.replace(
        settings, preset="off", randomise=False, fog_color=[int(c) for c in np.rint(colour)], **values
    )


class ImageNoise:
    """Applies `NoiseSettings` to rendered frames; holds only caches that depend on the image size."""

    def __init__(self, settings: NoiseSettings) -> None:
        settings = settings.resolved()
        _validate(settings)
        self.settings = settings
        self._fog_color = np.asarray(settings.fog_color, dtype=np.float32)
        self._distortion_maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._fog_fields: dict[tuple[int, int], np.ndarray] = {}

    def apply(
        self,
        image: np.ndarray,
        depth: np.ndarray | None,
        rng: np.random.Generator,
        motion_px: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """Return a degraded copy of ``image`` (uint8 HxWx3).

        ``depth`` is the per-pixel distance from the camera in metres (HxW, e.g. MuJoCo's depth buffer in metres;
        inf or nan = nothing hit, treated as infinitely far); required when fog or depth of field is on.
        ``motion_px`` is the apparent image motion (x right, y down) in pixels over one frame; it only matters
        when motion blur is on.
        """
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image must be uint8 HxWx3, got {image.dtype} {image.shape}")
        s = self.settings
        if not s.enabled:
            return image.copy()
        if s.needs_depth:
            depth = self._checked_depth(depth, image.shape[:2])
        out = image.astype(np.float32)
        if s.attenuation > 0:
            out = self._attenuate(out, depth)
        if s.fog > 0:
            out = self._fog(out, depth)
        if s.marine_snow > 0:
            out = _marine_snow(out, s.marine_snow, rng)
        if s.depth_of_field > 0:
            out = self._depth_of_field(out, depth)
        if s.motion_blur > 0:
            out = self._motion_blur(out, motion_px)
        if s.distortion > 0:
            out = self._distort(out)
        if s.shot_noise > 0:
            signal = np.sqrt(np.clip(out, 0.0, 255.0) / np.float32(255.0))
            out += rng.standard_normal(size=out.shape, dtype=np.float32) * signal * np.float32(s.shot_noise)
        if s.grain > 0:
            out += rng.standard_normal(size=(*out.shape[:2], 1), dtype=np.float32) * np.float32(s.grain)
        result = np.rint(np.clip(out, 0.0, 255.0)).astype(np.uint8)
        return _jpeg(result, s.jpeg_quality) if s.jpeg_quality > 0 else result

    @staticmethod
    def _checked_depth(depth: np.ndarray | None, size: tuple[int, int]) -> np.ndarray:
        if depth is None:
            raise ValueError("fog and depth of field need a depth map; render depth or switch them off")
        if depth.shape != size:
            raise ValueError(f"depth map shape {depth.shape} does not match image size {size}")
        return np.nan_to_num(depth.astype(np.float32, copy=False), nan=np.inf, posinf=np.inf)

    def _fog(self, image: np.ndarray, depth: np.ndarray) -> np.ndarray:
        visibility = np.exp(-np.square(np.float32(self.settings.fog) * depth))
        water = self._fog_fields.get(visibility.shape)
        if water is None:
            water = np.broadcast_to(self._fog_color, (*visibility.shape, 3)).copy()
            self._fog_fields[visibility.shape] = water
        return cv2.blendLinear(image, water, visibility, 1.0 - visibility)

    def _attenuate(self, image: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Per-channel decay with distance plus backscatter toward the water colour (far pixels become water)."""
        rates = np.float32(self.settings.attenuation) * np.asarray(self.settings.attenuation_rgb, dtype=np.float32)
        transmission = np.exp(-depth[..., None] * rates)
        return image * transmission + self._fog_color * (np.float32(1.0) - transmission)

    def _depth_of_field(self, image: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Blend a few Gaussian-blurred copies per pixel by its circle of confusion (cheaper than per-pixel kernels).

        Each pixel mixes the two blur levels around its confusion with tent weights; the running blend keeps
        the weight accumulated so far, so the result is the weighted sum without a per-level HxWx3 multiply.
        """
        radius = self.settings.depth_of_field
        with np.errstate(divide="ignore"):  # depth 0 gives inf: as out of focus as it gets
            confusion = np.minimum(np.abs(1.0 - np.float32(self.settings.focus_m) / depth), 1.0)
        levels = min(math.ceil(radius), _MAX_DOF_LEVELS)
        position = confusion * levels  # fractional index into the blur levels
        out = image
        total = np.maximum(0.0, 1.0 - position)  # weight of the sharp image
        for level in range(1, levels + 1):
            weight = np.maximum(0.0, 1.0 - np.abs(position - level))
            if not weight.any():
                continue
            sigma = radius * level / levels / 2.0  # the kernel spans about +-2 sigma = +-radius
            blurred = cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
            out = cv2.blendLinear(out, blurred, total, weight)
            total += weight
        return out

    def _motion_blur(self, image: np.ndarray, motion_px: tuple[float, float]) -> np.ndarray:
        smear = np.asarray(motion_px, dtype=np.float64) * self.settings.motion_blur
        length = float(np.hypot(*smear))
        if length < _MIN_MOTION_PX:
            return image
        kernel = _line_kernel(smear, length)
        return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT_101)

    def _distort(self, image: np.ndarray) -> np.ndarray:
        size = image.shape[:2]
        maps = self._distortion_maps.get(size)
        if maps is None:
            maps = _barrel_maps(size, self.settings.distortion)
            self._distortion_maps[size] = maps
        return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)


def _validate(settings: NoiseSettings) -> None:
    for name in EFFECTS:
        if getattr(settings, name) < 0:
            raise ValueError(f"noise setting {name} must be >= 0, got {getattr(settings, name)}")
    if settings.focus_m <= 0:
        raise ValueError(f"noise focus_m must be > 0, got {settings.focus_m}")
    if not 0.0 <= settings.clean_share <= 1.0:
        raise ValueError(f"noise clean_share must lie in [0, 1], got {settings.clean_share}")
    if settings.jpeg_quality < 0 or settings.jpeg_quality > _JPEG_BEST:
        raise ValueError(f"noise jpeg_quality must lie in 0..100 (0 = off), got {settings.jpeg_quality}")
    rates = list(settings.attenuation_rgb)
    if len(rates) != 3 or any(r < 0 for r in rates):
        raise ValueError(f"noise attenuation_rgb must be 3 values >= 0, got {rates}")
    color = list(settings.fog_color)
    if len(color) != 3 or any(not 0 <= c <= 255 for c in color):
        raise ValueError(f"noise fog_color must be 3 values in 0..255, got {color}")


def _marine_snow(image: np.ndarray, mean_count: float, rng: np.random.Generator) -> np.ndarray:
    """Blend a Poisson number of small bright discs (sub-pixel positions and radii) into the frame."""
    height, width = image.shape[:2]
    count = int(rng.poisson(mean_count))
    if count == 0:
        return image
    mask = np.zeros((height, width), dtype=np.float32)
    scale = 1 << _FIXED_POINT_BITS
    for x, y, radius, opacity in zip(
        rng.uniform(0, width, count), rng.uniform(0, height, count), rng.uniform(0.4, 1.2, count),
        rng.uniform(0.3, 0.9, count), strict=True,
    ):  # fmt: skip
        centre = (round(x * scale), round(y * scale))
        cv2.circle(mask, centre, max(1, round(radius * scale)), float(opacity), -1, cv2.LINE_AA, _FIXED_POINT_BITS)
    mask = np.minimum(mask, 1.0)[..., None]
    return image * (1.0 - mask) + _SNOW_COLOUR * mask


_SNOW_COLOUR = np.asarray([215, 225, 225], dtype=np.float32)  # particles lit by the camera's lights: near white


def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode and decode as the camera's JPEG encoder would (OpenCV works in BGR)."""
    ok, encoded = cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError(f"OpenCV could not JPEG-encode a {image.shape} frame")
    return cv2.imdecode(encoded, cv2.IMREAD_COLOR)[..., ::-1].copy()


def _line_kernel(smear: np.ndarray, length: float) -> np.ndarray:
    """A normalised kernel of a segment centred on the origin.

    Drawn on a supersampled canvas and area-averaged down, so sub-pixel lengths and directions weigh each
    pixel by how much of the segment crosses it.
    """
    half = math.ceil(length / 2.0) + 1
    size = 2 * half + 1
    canvas = np.zeros((size * _KERNEL_SUPERSAMPLING, size * _KERNEL_SUPERSAMPLING), dtype=np.float32)
    centre = half * _KERNEL_SUPERSAMPLING + (_KERNEL_SUPERSAMPLING - 1) / 2.0
    offset = smear * (_KERNEL_SUPERSAMPLING / 2.0)
    start, end = _fixed_point(centre - offset), _fixed_point(centre + offset)
    cv2.line(canvas, start, end, 1.0, 1, cv2.LINE_8, _FIXED_POINT_BITS)
    kernel = cv2.resize(canvas, (size, size), interpolation=cv2.INTER_AREA)
    kernel += kernel[::-1, ::-1]  # the segment is point-symmetric; remove the drawing's rounding bias
    return kernel / kernel.sum()


def _fixed_point(point: np.ndarray) -> tuple[int, int]:
    """A point as OpenCV's drawing functions take sub-pixel positions: integers with fractional bits."""
    scale = 1 << _FIXED_POINT_BITS
    return round(float(point[0]) * scale), round(float(point[1]) * scale)


def _barrel_maps(size: tuple[int, int], k1: float) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates for each output pixel: pushed outward by 1 + k1 r^2, so the frame's content bulges."""
    height, width = size
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    norm = max(width, height) / 2.0
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    dx, dy = xs - cx, ys - cy
    scale = 1.0 + k1 * (dx * dx + dy * dy) / (norm * norm)
    return (cx + dx * scale).astype(np.float32), (cy + dy * scale).astype(np.float32)
