"""The cross-modal VAE (CMVAE): one image encoder, an image decoder and a state decoder per label.

The encoder compresses a 64x64 RGB frame into a small latent z; the image
decoder keeps z faithful to the picture, and the state decoders tie the first
latent dimensions to the physical quantities the policy cares about
(z[0] -> d, z[1] -> theta, z[2] -> psi, and for the 3d task z[3] -> elevation). That tie is what lets a policy read
distance and bearing straight off z. Shapes and sizes follow SPEC.md
("CMVAE"); the checkpoint format lives here too, because a checkpoint is only
meaningful together with the architecture that reads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from encoder_service import DETECTOR_FORMAT
from services.geometry import ALPHA_DEG, BETA_DEG, LABEL_NAMES, VERTICAL_LABEL_NAMES
from services.messages import IMAGE_SHAPE as IMAGE_SHAPE  # re-exported: encoder_service.data reads it here

#: Physical range of every label a CMVAE can learn (d metres, angles degrees); each maps linearly onto [-1, 1].
LABEL_RANGES = {
    "d": (2.0, 10.0),
    "theta": (-ALPHA_DEG, ALPHA_DEG),
    "psi": (-180.0, 180.0),
    "elevation": (-BETA_DEG, BETA_DEG),
}
#: The label sets a CMVAE learns: the planar task's frames' (the paper's), or the 3d task's, elevation added.
LABEL_SETS = (LABEL_NAMES, VERTICAL_LABEL_NAMES)
PSI = LABEL_NAMES.index("psi")  # the one circular label
THETA = LABEL_NAMES.index("theta")
DISTANCE = LABEL_NAMES.index("d")
#: Labels a left-right flip of the frame negates (the target at -theta, facing -psi); d and the elevation keep theirs.
MIRROR_NEGATED = ("theta", "psi")

CHECKPOINT_FORMAT = "swimm-cmvae"
CHECKPOINT_VERSION = 1


# ---------------------------------------------------------------- labels and pixels


def label_ranges(names: tuple[str, ...] = LABEL_NAMES) -> np.ndarray:
    """(len(names), 2) physical (low, high) of each label, in the order named."""
    return np.array([LABEL_RANGES[name] for name in names], dtype=np.float64)


def check_label_names(names: tuple[str, ...] | list[str], where: str) -> tuple[str, ...]:
    """``names`` as a tuple if it is one of the label sets, else a ValueError naming ``where`` it came from."""
    if tuple(names) not in LABEL_SETS:
        sets = " or ".join(str(list(labels)) for labels in LABEL_SETS)
        raise ValueError(f"{where}: labels {list(names)!r}, expected {sets}")
    return tuple(names)


def normalise_labels(labels: np.ndarray, names: tuple[str, ...] = LABEL_NAMES) -> np.ndarray:
    """Physical rows (columns as ``names``: d m, theta deg, psi deg[, elevation deg]) -> [-1, 1] per column."""
    lo, hi = label_ranges(names).T
    return (2.0 * (np.asarray(labels, dtype=np.float64) - lo) / (hi - lo) - 1.0).astype(np.float32)


def denormalise_labels(normalised: np.ndarray, names: tuple[str, ...] = LABEL_NAMES) -> np.ndarray:
    """Inverse of :func:`normalise_labels`: [-1, 1] columns -> physical units, float32."""
    lo, hi = label_ranges(names).T
    return ((np.asarray(normalised, dtype=np.float64) + 1.0) * 0.5 * (hi - lo) + lo).astype(np.float32)


def label_errors(predicted: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Absolute errors per label in physical units; psi's error wraps to [0, 180] since yaw is circular."""
    errors = np.abs(np.asarray(predicted, dtype=np.float64) - np.asarray(true, dtype=np.float64))
    errors[:, PSI] = np.abs((errors[:, PSI] + 180.0) % 360.0 - 180.0)
    return errors


def check_images(images: np.ndarray) -> None:
    """Raise ValueError unless ``images`` is a uint8 array shaped (N, 64, 64, 3)."""
    if not isinstance(images, np.ndarray):
        raise ValueError(f"images must be a numpy array, got {type(images).__name__}")
    if images.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {images.dtype}")
    if images.ndim != 4 or images.shape[1:] != IMAGE_SHAPE or images.shape[0] == 0:
        raise ValueError(f"images must be shaped (N>0, {', '.join(map(str, IMAGE_SHAPE))}), got {images.shape}")


def images_to_tensor(images: np.ndarray | torch.Tensor, device: torch.device | str = "cpu") -> torch.Tensor:
    """uint8 NHWC frames -> float NCHW in [-1, 1], channels_last.

    The uint8 array crosses to the device before the float conversion (4x less
    to copy), and permuting a contiguous NHWC tensor to NCHW already *is* the
    channels_last layout, so no copy happens for the memory format.
    """
    batch = torch.from_numpy(np.ascontiguousarray(images)) if isinstance(images, np.ndarray) else images
    batch = batch.to(device, non_blocking=True).permute(0, 3, 1, 2)
    return (batch.float() / 127.5 - 1.0).contiguous(memory_format=torch.channels_last)


def tensor_to_images(images: torch.Tensor) -> np.ndarray:
    """Decoder output (NCHW in [-1, 1]) -> uint8 NHWC, for figures and pixel errors."""
    pixels = ((images.detach().float().clamp(-1.0, 1.0) + 1.0) * 127.5).round()
    return pixels.permute(0, 2, 3, 1).to("cpu", torch.uint8).numpy()


# ---------------------------------------------------------------- modules


class ResidualBlock(nn.Module):
    """Dronet's pre-activation block: two 3x3 convs (the first halves the size) plus a 1x1 stride-2 shortcut."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.branch = nn.Sequential(
            nn.BatchNorm2d(in_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1),
        )
        self.shortcut = nn.Conv2d(in_channels, out_channels, 1, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.branch(x) + self.shortcut(x)


#: The clean world's mean intensity per channel (0 to 1, over reset frames): the white balance's target, so a model
#: fine-tuned from one that read raw frames starts near what it knew.
REFERENCE_MEAN = (0.1043, 0.2862, 0.3415)


def frame_mean(images: torch.Tensor) -> torch.Tensor:
    """Each frame's channel means, (N, C, 1, 1). An exported graph takes the mean of the row means: onnxruntime's
    one-pass mean of a whole frame errs enough that a dark frame's white-balance gain carries it into the actions
    (docs/real.md); torch's own mean stays as it was, so its readings do too."""
    if torch.onnx.is_in_onnx_export():
        return images.mean(dim=3, keepdim=True).mean(dim=2, keepdim=True)
    return images.mean(dim=(2, 3), keepdim=True)


class WhiteBalance(nn.Module):
    """Each frame's channels scaled to the clean world's mean intensity (part of the ONNX graph)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("target", torch.tensor(REFERENCE_MEAN).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.balanced(images, images)

    def balanced(self, images: torch.Tensor, by: torch.Tensor) -> torch.Tensor:
        """``images`` scaled by the gain that brings ``by``'s channel means to the target."""
        mean = (frame_mean(by) + 1.0) * 0.5  # [-1, 1] -> [0, 1]
        # a black frame stays black, not NaN
        return (images + 1.0) * 0.5 * (self.target / mean.clamp_min(1e-3)) * 2.0 - 1.0


#: Side (pixels of a 64x64 frame) of the neighbourhood whose mean :class:`LocalContrast` takes away: wider than a
#: dolphin at 4 m, narrower than a light shaft's wedge.
LOCAL_WINDOW = 17


class LocalContrast(WhiteBalance):
    """Each pixel's neighbourhood mean replaced by the frame's mean, then the white balance: light added to part of
    the frame is taken away, and what differs from its surroundings stays (part of the ONNX graph)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        evened, _ = self.evened(images)
        return self.balanced(evened, evened)

    def evened(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the frame with each pixel's neighbourhood mean replaced by the frame's mean, those means)."""
        pad = LOCAL_WINDOW // 2
        padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
        # A box mean is separable: a row pass and a column pass cost 2k, not k^2, per pixel.
        local = F.avg_pool2d(F.avg_pool2d(padded, (1, LOCAL_WINDOW), stride=1), (LOCAL_WINDOW, 1), stride=1)
        return images - local + frame_mean(images), local


class LocalContrastAndLight(LocalContrast):
    """:class:`LocalContrast`'s evened frame and, as channels 3 to 5, the neighbourhood means it took away, both
    scaled by the evened frame's gain: together they hold what the white-balanced frame holds, the light apart
    from the detail (part of the ONNX graph)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        evened, local = self.evened(images)
        return torch.cat([self.balanced(evened, evened), self.balanced(local, evened)], dim=1)


#: How the encoder normalises its input: ``none`` reads the frame as it is (every model before input norms);
#: ``channel`` white-balances it (gray world: each colour channel scaled so its mean is the clean world's), so a
#: tint or a brightness the water gives a whole frame is gone before the first convolution, while the dolphin's
#: contrast against the water, a distance cue, stays (docs/encoder.md). ``local`` first evens out light that varies
#: across the frame (light shafts, a glowing surface) by taking away each pixel's neighbourhood mean, then
#: white-balances: a shaft keeps only its edges, the dolphin its contrast against what surrounds it. ``light`` is
#: ``local`` with the light it took away beside it, as three more channels: the evened frame for where the dolphin
#: is, a coarse copy of the light for what the water's haze says of distance.
NORMALISERS = {"none": nn.Identity, "channel": WhiteBalance, "local": LocalContrast, "light": LocalContrastAndLight}
INPUT_NORMS = tuple(NORMALISERS)


def input_channels(input_norm: str, track: bool, prior_distance: bool = False) -> tuple[str, ...]:
    """The first convolution's input channels by name: the normalised frame's colours, a tracking encoder's prior
    stripe (and its distance plane), the light's colours. Starting a model from another matches its weights by
    these names."""
    light = ("light red", "light green", "light blue") if input_norm == "light" else ()
    prior = (("prior",) if track else ()) + (("prior distance",) if prior_distance else ())
    return ("red", "green", "blue") + prior + light


def mirror_signs(labels: tuple[str, ...], n_z: int) -> tuple[float, ...]:
    """Per latent, how a left-right flip of the frame changes it: -1 for the labels it negates, +1 for the rest
    (the other labels and the latents no label ties, which the mirror average then makes symmetric)."""
    return tuple(-1.0 if i < len(labels) and labels[i] in MIRROR_NEGATED else 1.0 for i in range(n_z))


class CircularPsiReader(nn.Module):
    """psi's mirror average taken round the circle. A plain mirror average averages psi's latent with the mirror
    image's, negated; a dolphin seen from behind that one read puts at +179 deg and the other at -179 then reads
    near 0, facing the camera. This decodes both reads through a table of the psi decoder, takes their circular
    mean, and gives the latent on the table that decodes nearest it (docs/encoder.md, "Stage j"). It holds no
    weight: :meth:`tabulate` fills the table from a decoder, and checkpoints stay as they were."""

    SPAN = 8.0  # latents read beyond +-SPAN are clamped to it; a KL-held latent stays well inside
    POINTS = 6401  # a step of 0.0025 in the latent: its psi error is far below the encoder's own

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("grid", torch.linspace(-self.SPAN, self.SPAN, self.POINTS), persistent=False)
        self.register_buffer("cosines", torch.ones(self.POINTS), persistent=False)  # of the angle each grid point
        self.register_buffer("sines", torch.zeros(self.POINTS), persistent=False)  # decodes to

    @torch.no_grad()
    def tabulate(self, decoder: nn.Module) -> None:
        angles = math.pi * decoder(self.grid[:, None])[:, 0]  # normalised psi -> radians
        self.cosines.copy_(torch.cos(angles))
        self.sines.copy_(torch.sin(angles))

    def forward(self, own: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
        """psi latents (N,) of the frames and of their mirror images, as read -> (N,) latents whose psi is the
        circular mean of the frame's psi and the mirror's, negated."""
        own_at, mirror_at = self._nearest(own), self._nearest(mirror)
        cosine = self.cosines[own_at] + self.cosines[mirror_at]  # cos(-a) = cos(a)
        sine = self.sines[own_at] - self.sines[mirror_at]  # sin(-a) = -sin(a): the mirror's psi negated
        # the grid point whose angle lies nearest the mean direction: the largest dot product with it
        nearest = (cosine[:, None] * self.cosines + sine[:, None] * self.sines).argmax(dim=1)
        return self.grid[nearest]

    def _nearest(self, latents: torch.Tensor) -> torch.Tensor:
        """The grid index nearest each latent (N,)."""
        step = (self.grid[-1] - self.grid[0]) / (self.POINTS - 1)
        return ((latents - self.grid[0]) / step).round().clamp(0, self.POINTS - 1).long()


#: Layers of ``ImageEncoder.features`` up to the first residual block: their 8x8 map is what the mask head reads.
MASK_TAP = 3


#: Half-width (image units, the frame spans [-1, 1]) of the stripe a tracking encoder's prior channel draws: ~3 px.
PRIOR_WIDTH = 0.1


def prior_map(azimuth_deg: torch.Tensor, size: int = IMAGE_SHAPE[0]) -> torch.Tensor:
    """Azimuths (N,) or (N, 1) in degrees (+ = left) -> (N, 1, size, size) in [-1, 1]: a vertical stripe at the
    column where a target at that azimuth appears in the pinhole camera, -1 elsewhere."""
    azimuth = azimuth_deg.reshape(-1, 1).float()
    column = -torch.tan(azimuth * (math.pi / 180.0)) / math.tan(math.radians(ALPHA_DEG))
    columns = torch.linspace(-1 + 1 / size, 1 - 1 / size, size, device=azimuth.device)
    stripe = torch.exp(-0.5 * ((columns[None, :] - column) / PRIOR_WIDTH) ** 2)  # (N, size)
    return (2.0 * stripe - 1.0)[:, None, None, :].expand(-1, 1, size, size)


def distance_map(distance_m: torch.Tensor, size: int = IMAGE_SHAPE[0]) -> torch.Tensor:
    """Distances (N,) in metres -> (N, 1, size, size): a plane at the distance normalised as the d label is; the
    engagement prior's 0 m (the target not yet seen) draws -1.5, below any distance the encoder reads."""
    low, high = LABEL_RANGES["d"]
    level = (2.0 * (distance_m.reshape(-1, 1, 1, 1).float() - low) / (high - low)) - 1.0
    level = torch.where(distance_m.reshape(-1, 1, 1, 1) > 0, level, torch.full_like(level, -1.5))
    return level.expand(-1, 1, size, size)


def with_prior(images: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """A tracking encoder's input: the (N, 3, H, W) frames and the prior's stripe as a fourth channel; a prior
    (N, 2) of azimuth and distance adds the distance plane as a fifth."""
    prior, size = prior.to(images.device), images.shape[-1]
    planes = [images, prior_map(prior if prior.dim() == 1 else prior[:, 0], size).to(images.dtype)]
    if prior.dim() == 2:
        planes.append(distance_map(prior[:, 1], size).to(images.dtype))
    return torch.cat(planes, dim=1).contiguous(memory_format=torch.channels_last)


#: The training prior's spread about the target's true azimuth, degrees: a step's reading error and motion mostly,
#: a wider miss (a re-acquisition, a fast turn) in a share of frames. Wider than the loop's own misses, so the
#: encoder reads the azimuth off the image and takes from the prior only which dolphin: trained at (3, 8) deg and a
#: fifth wide, it leant on the prior and lagged the target in closed loop (docs/encoder.md, pods).
PRIOR_JITTER_DEG = (5.0, 10.0)
PRIOR_WIDE_SHARE = 0.3
#: A distance prior's spread, a share of the distance: the loop's own distance reads are off by about a metre
#: (docs/encoder.md, pods); the wide share is drawn as the azimuth's is.
PRIOR_DISTANCE_JITTER = (0.1, 0.25)
#: The share of frames whose target is the dolphin nearest the image centre that get the engagement prior instead,
#: exactly the centre (0 deg), as the loop's first frame does: without them the encoder never saw a centre prior far
#: from its target, and lost it at engagement when the nearest dolphin was well off the centre (docs/encoder.md).
ENGAGEMENT_SHARE = 0.2
#: Validation and evaluation draw their priors from this seed, so every epoch's and model's scores read the same.
EVALUATION_PRIORS_SEED = 0


class PriorReader(nn.Module):
    """A tracking CMVAE as the inference engines run it: (frames (N, 3, H, W), priors (N,) degrees) ->
    (mu, logvar, next priors (N,) degrees); the stripe is drawn inside, so the ONNX file takes the prior as the
    azimuth it is. A model whose prior holds the distance too takes and gives priors (N, 2): degrees, metres.

    The next prior is what the latent decodes to, computed here so that the engines and the exported policy
    file give it alike.
    """

    def __init__(self, cmvae: CMVAE) -> None:
        super().__init__()
        self.encoder = cmvae.encoder
        self.prior_labels = cmvae.prior_labels
        self.columns = [cmvae.labels.index(label) for label in self.prior_labels]
        self.decoders = nn.ModuleList(cmvae.state_decoders[column] for column in self.columns)

    def forward(self, images: torch.Tensor, prior: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mu, logvar = self.encoder(with_prior(images, prior))
        read = []
        for label, column, decoder in zip(self.prior_labels, self.columns, self.decoders, strict=True):
            low, high = LABEL_RANGES[label]  # denormalise_labels, in torch for the engines' graphs
            read.append((decoder(mu[:, column : column + 1])[:, 0] + 1.0) * (0.5 * (high - low)) + low)
        return mu, logvar, read[0] if len(read) == 1 else torch.stack(read, dim=1)


def jittered_priors(azimuth_deg: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Training priors (N,) float32: each target's true azimuth plus a miss drawn as :data:`PRIOR_JITTER_DEG` says."""
    azimuth = np.asarray(azimuth_deg, dtype=np.float64)
    spread = np.where(rng.random(len(azimuth)) < PRIOR_WIDE_SHARE, *PRIOR_JITTER_DEG[::-1])
    return (azimuth + rng.normal(size=len(azimuth)) * spread).astype(np.float32)


def training_priors(
    azimuth_deg: np.ndarray,
    centred: np.ndarray | None,
    rng: np.random.Generator,
    distance_m: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`jittered_priors`, but :data:`ENGAGEMENT_SHARE` of the frames whose target is the dolphin nearest the
    image centre (``centred``, bool (N,); None: every frame's, a lone dolphin's) get the engagement prior, 0 deg.
    The share is drawn for every frame, so which frames qualify never shifts the other draws. With the targets'
    distances, priors (N, 2): each distance off by :data:`PRIOR_DISTANCE_JITTER` of itself, the engagement
    prior's 0 m (not yet seen); drawn after the azimuths, so those are the same with or without."""
    priors = jittered_priors(azimuth_deg, rng)
    engaged = rng.random(len(priors)) < ENGAGEMENT_SHARE
    if centred is not None:
        engaged &= np.asarray(centred, dtype=bool)
    priors[engaged] = 0.0
    if distance_m is None:
        return priors
    distance = np.asarray(distance_m, dtype=np.float64)
    spread = np.where(rng.random(len(distance)) < PRIOR_WIDE_SHARE, *PRIOR_DISTANCE_JITTER[::-1])
    distance = np.clip(distance * (1.0 + rng.normal(size=len(distance)) * spread), *LABEL_RANGES["d"])
    distance[engaged] = 0.0
    return np.stack([priors, distance.astype(np.float32)], axis=1)


def encoder_input(
    model: CMVAE,
    frames: np.ndarray,
    labels: np.ndarray,
    device: torch.device | str,
    rng: np.random.Generator,
    centred: np.ndarray | None = None,
) -> torch.Tensor:
    """uint8 frames as ``model``'s encoder reads them in training and evaluation: a tracking model's with
    :func:`training_priors` about the true azimuths (``labels``, physical, d and theta in columns 0 and 1) as the
    stripe (and the distance plane), the engagement prior on a share of the frames ``centred`` (a batch's) marks."""
    images = images_to_tensor(frames, device)
    if not model.tracks:
        return images
    distance = labels[:, DISTANCE] if model.prior_distance else None
    return with_prior(images, torch.from_numpy(training_priors(labels[:, THETA], centred, rng, distance)))


class ImageEncoder(nn.Module):
    """q(z | image): 64x64x3 -> (mu, logvar), each (N, n_z).

    With ``track`` the input has a fourth channel, :func:`prior_map`'s stripe at where the target was last seen,
    and the first three latents describe the dolphin under that stripe: the one the rover follows, among others
    that look alike (docs/encoder.md, pods). The loop hands each frame its prior (the azimuth the previous frame's
    latent decodes to, the image centre at an episode's first frame), so the encoder itself keeps no state.

    With ``locate`` a :class:`MaskHead` (the locator) maps the 8x8 feature map to where the dolphin is, and the
    head reads, beside the pooled features, that map's soft-argmax: the expected column and row of the dolphin
    in [-1, 1]. The azimuth then has a path from where the animal is, not only from the 2x2 map at the end,
    which a bright structure elsewhere in the frame can sway. Trained with ``--mask-weight``, the locator learns
    the dataset's masks.

    With ``mirror_signs`` (one +-1 per latent) the encoder reads each frame and its left-right mirror image and
    averages the two readings, the mirror's latents multiplied by those signs (-1 where a flip negates the
    label). The latents are then exactly as symmetric as the world: a dolphin dead ahead reads theta 0, where a
    single reading can sit to one side, and the tracker and a policy hold the dolphin there (docs/encoder.md).
    With ``psi_reader`` as well, psi (z[PSI]) is averaged round the circle (:class:`CircularPsiReader`).
    """

    FEATURES = 128 * 2 * 2  # the flattened 2x2 map after the last residual block

    def __init__(
        self,
        n_z: int,
        input_norm: str = "none",
        locate: bool = False,
        track: bool = False,
        mirror_signs: tuple[float, ...] | None = None,
        prior_distance: bool = False,
        psi_reader: CircularPsiReader | None = None,
    ) -> None:
        super().__init__()
        if psi_reader is not None and mirror_signs is None:
            raise ValueError("psi averaged round the circle is a mirror average's: psi_reader needs mirror_signs")
        if mirror_signs is not None and len(mirror_signs) != n_z:
            raise ValueError(f"mirror_signs needs one sign per latent ({n_z}), got {len(mirror_signs)}")
        if input_norm not in INPUT_NORMS:
            raise ValueError(f"input_norm must be one of {', '.join(INPUT_NORMS)}, got {input_norm!r}")
        self.input_norm = input_norm
        if prior_distance and not track:
            raise ValueError("a distance prior is a tracking encoder's: prior_distance needs track")
        self.tracks = track
        self.prior_distance = prior_distance
        self.normalise = NORMALISERS[input_norm]()
        self.input_channels = input_channels(input_norm, track, prior_distance)
        self.features = nn.Sequential(
            nn.Conv2d(len(self.input_channels), 32, 5, stride=2, padding=2),  # 64 -> 32
            nn.MaxPool2d(3, stride=2, padding=1),  # 32 -> 16
            ResidualBlock(32, 32),  # 16 -> 8
            ResidualBlock(32, 64),  # 8 -> 4
            ResidualBlock(64, 128),  # 4 -> 2
            nn.Flatten(),
            nn.ReLU(inplace=True),  # the blocks end pre-activation
        )
        self.locator = MaskHead() if locate else None
        self.head = nn.Sequential(
            nn.Linear(self.FEATURES + (2 if locate else 0), 64),
            nn.ReLU(inplace=True),
            nn.Linear(64, 32),
            nn.ReLU(inplace=True),
            nn.Linear(32, 2 * n_z),
        )
        self.n_z = n_z
        self.mirror_signs: torch.Tensor | None
        signs = None if mirror_signs is None else torch.tensor(mirror_signs, dtype=torch.float32)
        self.register_buffer("mirror_signs", signs, persistent=False)  # not a weight: checkpoints stay as they were
        self.psi_reader = psi_reader

    @property
    def mirror_averages(self) -> bool:
        return self.mirror_signs is not None

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, logvar, _, _ = self.with_feature_map(images)
        return mu, logvar

    def with_feature_map(
        self, images: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(mu, logvar) as ``forward`` gives them, the 8x8 map after the first residual block (N, 32, 8, 8), and
        the locator's logits (N, 8, 8) (None without one); a mirror-averaging encoder's map and logits are the
        frames' own, not their mirror images'."""
        count = images.shape[0]
        if self.mirror_signs is not None:
            images = torch.cat([images, images.flip(-1)])  # NCHW: -1 is the width; a prior stripe flips with it
        feature_map = self.features[:MASK_TAP](self._normalised(images))
        pooled = self.features[MASK_TAP:](feature_map)
        where = None
        if self.locator is not None:
            where = self.locator(feature_map)
            pooled = torch.cat([pooled, soft_argmax(where)], dim=1)
        mu, logvar = self._split(self.head(pooled))
        if self.mirror_signs is not None:
            own, mirror = mu[:count], mu[count:]
            mu = (own + self.mirror_signs * mirror) / 2
            if self.psi_reader is not None:
                psi = self.psi_reader(own[:, PSI], mirror[:, PSI])  # every label set reads psi at PSI
                mu = torch.cat([mu[:, :PSI], psi[:, None], mu[:, PSI + 1 :]], dim=1)
            logvar = (logvar[:count] + logvar[count:]) / 2
            feature_map, where = feature_map[:count], None if where is None else where[:count]
        return mu, logvar, feature_map, where

    def _normalised(self, images: torch.Tensor) -> torch.Tensor:
        """The input norm applied to the colour channels; a tracking encoder's prior stripe passes as it is, in
        the place :func:`input_channels` gives it."""
        if not self.tracks:
            return self.normalise(images)
        normalised = self.normalise(images[:, :3])
        return torch.cat([normalised[:, :3], images[:, 3:], normalised[:, 3:]], dim=1)

    def _split(self, stats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return stats[:, : self.n_z], stats[:, self.n_z :]


class MaskHead(nn.Module):
    """Where the dolphin is: the encoder's 8x8 feature map -> mask logits (N, 8, 8), a training aid only.

    Its loss asks the encoder's early features to find the animal rather than the scene around it; the
    latent and the inference path (``ImageEncoder.forward``) never see it.
    """

    SIZE = 8

    def __init__(self, channels: int = 32) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.ReLU(),  # not in place: the map also feeds the encoder's next block
            nn.Conv2d(channels, channels, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(channels, 1, 1),
        )

    def forward(self, feature_map: torch.Tensor) -> torch.Tensor:
        return self.layers(feature_map)[:, 0]


def soft_argmax(logits: torch.Tensor) -> torch.Tensor:
    """The expected (column, row) in [-1, 1] (left/top = -1) under a softmax over the cells of ``logits``
    (N, H, W): (N, 2)."""
    height, width = logits.shape[-2:]
    weights = torch.softmax(logits.flatten(1), dim=1).view_as(logits)
    columns = torch.linspace(-1 + 1 / width, 1 - 1 / width, width, device=logits.device, dtype=logits.dtype)
    rows = torch.linspace(-1 + 1 / height, 1 - 1 / height, height, device=logits.device, dtype=logits.dtype)
    return torch.stack([(weights.sum(dim=1) * columns).sum(dim=1), (weights.sum(dim=2) * rows).sum(dim=1)], dim=1)


class ImageDecoder(nn.Module):
    """p(image | z): dense 1024 -> 1x1x1024 -> six stride-2 transposed convs -> 64x64x3 in [-1, 1]."""

    CHANNELS = (1024, 256, 128, 64, 32, 16, 3)

    def __init__(self, n_z: int) -> None:
        super().__init__()
        self.dense = nn.Sequential(nn.Linear(n_z, self.CHANNELS[0]), nn.ReLU(inplace=True))
        layers: list[nn.Module] = []
        pairs = list(zip(self.CHANNELS[:-1], self.CHANNELS[1:], strict=True))
        for index, (c_in, c_out) in enumerate(pairs):
            layers.append(nn.ConvTranspose2d(c_in, c_out, 4, stride=2, padding=1))  # doubles the size
            if index < len(pairs) - 1:
                layers += [nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
        layers.append(nn.Tanh())
        self.deconv = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.deconv(self.dense(z).view(-1, self.CHANNELS[0], 1, 1))


class StateDecoder(nn.Module):
    """p(s_i | z[i]): one latent scalar -> one normalised label, through a 64-32 MLP."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(1, 64), nn.ReLU(inplace=True), nn.Linear(64, 32), nn.ReLU(inplace=True), nn.Linear(32, 1)
        )

    def forward(self, z_i: torch.Tensor) -> torch.Tensor:
        return self.mlp(z_i)


@dataclass
class CMVAEOutput:
    mu: torch.Tensor  # (N, n_z)
    logvar: torch.Tensor  # (N, n_z)
    z: torch.Tensor  # (N, n_z): a sample in training, mu in eval
    image: torch.Tensor  # (N, 3, 64, 64) in [-1, 1]
    state: torch.Tensor  # (N, labels) normalised (d, theta, psi[, elevation])
    mask: torch.Tensor | None = None  # (N, 8, 8) mask logits, models with a mask head only


class CMVAE(nn.Module):
    """Image encoder, image decoder and a state decoder per label, trained jointly."""

    def __init__(
        self,
        n_z: int = 10,
        input_norm: str = "none",
        mask_head: bool = False,
        labels: tuple[str, ...] = LABEL_NAMES,
        locate: bool = False,
        track: bool = False,
        mirror_average: bool = False,
        prior_distance: bool = False,
        circular_psi: bool = False,
    ) -> None:
        super().__init__()
        self.labels = check_label_names(labels, "CMVAE")
        if circular_psi and not mirror_average:
            raise ValueError("circular_psi averages psi's mirror reads round the circle: it needs mirror_average")
        if n_z < len(self.labels):
            raise ValueError(f"n_z must be at least {len(self.labels)} (one latent per label), got {n_z}")
        if mask_head and locate:
            raise ValueError("a CMVAE that locates the dolphin trains its locator on the masks: no mask head besides")
        self.n_z = n_z
        self.input_norm = input_norm
        signs = mirror_signs(self.labels, n_z) if mirror_average else None
        psi_reader = CircularPsiReader() if circular_psi else None
        self.encoder = ImageEncoder(n_z, input_norm, locate, track, signs, prior_distance, psi_reader)
        self.image_decoder = ImageDecoder(n_z)
        self.state_decoders = nn.ModuleList(StateDecoder() for _ in self.labels)
        self._tabulate_psi()
        # made last, so a model without it draws every other weight as before the head existed
        self.mask_head = MaskHead() if mask_head else None

    def encode(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.encoder(images)

    @property
    def locates(self) -> bool:
        return self.encoder.locator is not None

    @property
    def tracks(self) -> bool:
        """Whether the encoder reads a prior (:func:`with_prior`) beside each frame."""
        return self.encoder.tracks

    @property
    def prior_distance(self) -> bool:
        """Whether a tracking encoder's prior holds the target's last distance beside its azimuth."""
        return self.encoder.prior_distance

    @property
    def prior_labels(self) -> tuple[str, ...]:
        """The labels a tracking encoder's prior carries, in the prior's order: what its latent read last."""
        return ("theta", "d") if self.prior_distance else ("theta",)

    @property
    def prior_shape(self) -> tuple[int, ...]:
        """One frame's prior: a scalar azimuth, or (azimuth, distance)."""
        return (2,) if self.prior_distance else ()

    @property
    def mirror_averages(self) -> bool:
        """Whether the encoder averages each frame's reading with its mirror image's (``mirror_signs``)."""
        return self.encoder.mirror_averages

    @property
    def circular_psi(self) -> bool:
        """Whether the mirror average takes psi round the circle (:class:`CircularPsiReader`)."""
        return self.encoder.psi_reader is not None

    def load_state_dict(self, state_dict: Any, strict: bool = True, assign: bool = False) -> Any:
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._tabulate_psi()  # the circular psi read's table follows the psi decoder it was loaded with
        return result

    def _tabulate_psi(self) -> None:
        if self.encoder.psi_reader is not None:
            self.encoder.psi_reader.tabulate(self.state_decoders[PSI])

    def encode_with_mask(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(mu, logvar) and the mask logits (N, 8, 8) of the mask head or the locator, or None with neither."""
        if self.mask_head is None and not self.locates:
            return *self.encode(images), None
        mu, logvar, feature_map, where = self.encoder.with_feature_map(images)
        return mu, logvar, where if self.mask_head is None else self.mask_head(feature_map)

    def decode_image(self, z: torch.Tensor) -> torch.Tensor:
        return self.image_decoder(z)

    def decode_state(self, z: torch.Tensor) -> torch.Tensor:
        """Normalised labels from the first latent dimensions: (d, theta, psi[, elevation]) from z[0], z[1], ..."""
        return torch.cat([decoder(z[:, i : i + 1]) for i, decoder in enumerate(self.state_decoders)], dim=1)

    def forward(self, images: torch.Tensor, sample: bool | None = None) -> CMVAEOutput:
        """Encode, draw z (reparameterised; only while training unless ``sample`` says otherwise), decode both ways."""
        mu, logvar, mask = self.encode_with_mask(images)
        sample = self.training if sample is None else sample
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
        return CMVAEOutput(mu=mu, logvar=logvar, z=z, image=self.decode_image(z), state=self.decode_state(z), mask=mask)


# ---------------------------------------------------------------- loss


@dataclass
class LossParts:
    total: torch.Tensor
    image: torch.Tensor
    state: torch.Tensor
    kl: torch.Tensor
    mask: torch.Tensor | None = None  # the mask head's loss, when it is trained

    def as_floats(self) -> dict[str, float]:
        names = ("total", "image", "state", "kl") + (("mask",) if self.mask is not None else ())
        return {name: float(getattr(self, name).detach()) for name in names}


def state_errors(predicted: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Normalised label errors, psi's taken the short way round the circle, into [-1, 1).

    psi = +180 and -180 deg are one pose, normalised to +1 and -1. A plain difference calls a dolphin
    seen from behind at 179 deg and predicted at -179 wrong by almost the whole range, so whenever the
    view cannot tell the two apart (often, at 64 px) the mean square is least at 0, a dolphin facing the
    camera: z[2] then learns nothing of psi (the first shipped model did, MAE 90 deg). Wrapped, both
    answers are right.
    """
    errors = predicted - labels
    psi = torch.remainder(errors[:, PSI : PSI + 1] + 1.0, 2.0) - 1.0
    return torch.cat([errors[:, :PSI], psi, errors[:, PSI + 1 :]], dim=1)


STATE_LOSSES = ("mse", "l1")


def check_state_loss(name: str, called: str) -> None:
    """Refuse an unknown loss of one label, naming it as the caller knows it (``called``: the argument or the flag)."""
    if name not in STATE_LOSSES:
        raise ValueError(f"{called} {name!r}: expected one of {', '.join(STATE_LOSSES)}")


@dataclass(frozen=True)
class StateLoss:
    """How the state decoders' errors are scored: psi's and theta's square (the SPEC's) or absolute error, and a
    weight per label.

    The normalised labels' squares are small next to psi's absolute error, so with ``psi="l1"`` psi's pull on the
    shared encoder dwarfs distance's; ``weights`` (d, theta, psi, and the elevation for a vertical model) let a
    training stage set that balance. A label given no weight (the elevation, of three) weighs 1. ``theta="l1"``
    pulls as hard on a degree's error near the image centre as on a large one, where the square hardly pulls at all:
    the reward's azimuth penalty is steepest there.
    """

    psi: str = "mse"
    weights: tuple[float, ...] = (1.0, 1.0, 1.0)
    theta: str = "mse"

    def __post_init__(self) -> None:
        check_state_loss(self.psi, "psi_loss")
        check_state_loss(self.theta, "theta_loss")
        weights = tuple(self.weights)
        if (
            len(weights) not in (len(LABEL_NAMES), len(VERTICAL_LABEL_NAMES))
            or not all(math.isfinite(w) and w >= 0.0 for w in weights)
            or not any(weights)
        ):
            raise ValueError(
                f"state weights {list(weights)}: expected three finite weights >= 0 (d, theta, psi) or four (and the "
                "elevation), not all 0"
            )
        object.__setattr__(self, "weights", tuple(float(w) for w in weights))

    def __call__(self, predicted: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """The weighted mean over frames and labels of the squared normalised errors (absolute where ``l1``)."""
        errors = state_errors(predicted, labels)
        absolute = torch.zeros(errors.shape[1], dtype=torch.bool, device=errors.device)
        absolute[[column for column, loss in ((THETA, self.theta), (PSI, self.psi)) if loss == "l1"]] = True
        terms = torch.where(absolute, errors.abs(), errors.pow(2))
        if len(self.weights) > terms.shape[1]:
            raise ValueError(f"state weights {list(self.weights)} for a model of {terms.shape[1]} labels")
        weights = self.weights + (1.0,) * (terms.shape[1] - len(self.weights))
        return (terms * terms.new_tensor(weights)).mean()


#: The SPEC's state error: every label's square, equally weighted.
SPEC_STATE_LOSS = StateLoss()


def pool_masks(masks: torch.Tensor, size: int) -> torch.Tensor:
    """bool (N, 64, 64) -> float (N, size, size): a cell shows the dolphin if any of its pixels does."""
    return F.adaptive_max_pool2d(masks[:, None].float(), size)[:, 0]


def mask_loss(logits: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy of mask logits against the masks any-pooled to their size, positives reweighted.

    A far dolphin fills one or two of the 64 cells, so unweighted "nowhere" is a cheap near-optimum; weighting
    each positive cell by the batch's negatives per positive makes the animal's cells and the water count alike.
    """
    target = pool_masks(masks, logits.shape[-1])
    positives = target.sum()
    pos_weight = (target.numel() - positives) / positives.clamp_min(1.0)
    return F.binary_cross_entropy_with_logits(logits, target, pos_weight=pos_weight)


def mask_overlap(logits: torch.Tensor, masks: torch.Tensor) -> tuple[float, float]:
    """(intersection, union) cell counts of the predicted (logit > 0) and the any-pooled true masks."""
    predicted, target = logits > 0, pool_masks(masks, logits.shape[-1]) > 0
    return float((predicted & target).sum()), float((predicted | target).sum())


def cmvae_loss(
    outputs: CMVAEOutput,
    images: torch.Tensor,
    labels: torch.Tensor,
    beta: float,
    state_loss: StateLoss = SPEC_STATE_LOSS,
    masks: torch.Tensor | None = None,
    mask_weight: float = 0.0,
) -> LossParts:
    """Image MSE (pixels in [-1, 1]) + state MSE (normalised labels, psi wrapped) + beta * KL per image value.

    Both MSEs are means over their elements, so the KL (summed over latent
    dimensions, averaged over the batch) is divided by the number of values
    in one image: beta then weighs the KL against the image term as in a
    VAE whose reconstruction error is summed over pixels. Without it, the
    SPEC's beta = 8 outweighs a per-pixel mean MSE by four orders of
    magnitude and the latent collapses onto the prior (every prediction at
    the label mean; measured: psi MAE 90 deg). See docs/encoder.md.

    ``StateLoss(psi="l1")`` takes psi's absolute error instead of its square. Where
    a view cannot tell a dolphin facing the camera from one facing away, the
    square is least halfway between the two (wrong by 90 deg either way); the
    absolute error is least at the likelier of the two, and its mean is the
    MAE that the encoder is judged by.

    With ``mask_weight`` > 0 the mask head's :func:`mask_loss` against ``masks`` (bool (N, 64, 64)) is added.
    """
    image = F.mse_loss(outputs.image, images)
    state = state_loss(outputs.state, labels)
    kl = (-0.5 * (1.0 + outputs.logvar - outputs.mu.pow(2) - outputs.logvar.exp()).sum(dim=1)).mean()
    kl_per_value = kl / images[0].numel()
    parts = LossParts(total=image + state + beta * kl_per_value, image=image, state=state, kl=kl)
    return add_mask_loss(parts, outputs.mask, masks, mask_weight)


def add_mask_loss(
    parts: LossParts | DistillationParts, logits: torch.Tensor | None, masks: torch.Tensor | None, mask_weight: float
) -> LossParts | DistillationParts:
    """``parts`` with ``mask_weight`` x :func:`mask_loss` in its total; untouched (no term, same sum) at weight 0."""
    if mask_weight <= 0:
        return parts
    if logits is None or masks is None:
        raise ValueError("mask_weight > 0 needs a model with a mask head and the frames' masks")
    parts.mask = mask_loss(logits, masks)
    parts.total = parts.total + mask_weight * parts.mask
    return parts


@dataclass
class DistillationParts:
    total: torch.Tensor
    latent: torch.Tensor
    state: torch.Tensor
    prediction: torch.Tensor  # (N, 3): the normalised (d, theta, psi) the student's mu decodes to
    mask_logits: torch.Tensor | None = None  # (N, 8, 8): the student's mask head, when it has one
    mask: torch.Tensor | None = None  # the mask head's loss, when it is trained
    consistency: torch.Tensor | None = None  # the augmented frames' reads against the plain ones', when trained

    def as_floats(self) -> dict[str, float]:
        optional = tuple(name for name in ("mask", "consistency") if getattr(self, name) is not None)
        return {name: float(getattr(self, name).detach()) for name in ("total", "latent", "state", *optional)}


def distillation_loss(
    student: CMVAE,
    images: torch.Tensor,
    teacher_mu: torch.Tensor,
    teacher_logvar: torch.Tensor,
    labels: torch.Tensor,
    latent_weight: float,
    state_loss: StateLoss = SPEC_STATE_LOSS,
    masks: torch.Tensor | None = None,
    mask_weight: float = 0.0,
) -> DistillationParts:
    """Latent matching plus the state error: the student's posterior of a frame against the teacher's of its clean twin.

    The latent term is the mean squared difference of mu and of log-variance over all latent dimensions; the
    state term reads the student's mu through its (frozen) state decoders, so where a noisy frame cannot give
    the teacher's latent back exactly, the error goes where the labels say it costs least. The image decoder is
    not run: a latent that matches the teacher's decodes as the teacher's does, and the decoder is most of the compute.
    With ``mask_weight`` > 0 the student's mask head learns ``masks`` too (:func:`add_mask_loss`).
    """
    mu, logvar, mask_logits = student.encode_with_mask(images)
    latent = F.mse_loss(mu, teacher_mu) + F.mse_loss(logvar, teacher_logvar)
    prediction = student.decode_state(mu)
    state = state_loss(prediction, labels)
    parts = DistillationParts(
        total=latent_weight * latent + state, latent=latent, state=state, prediction=prediction, mask_logits=mask_logits
    )
    return add_mask_loss(parts, mask_logits, masks, mask_weight)


def add_consistency_loss(
    parts: DistillationParts, student: CMVAE, plain_images: torch.Tensor, weight: float
) -> DistillationParts:
    """``parts`` with ``weight`` x the mean squared gap between the student's (normalised) d and theta read of each
    augmented frame and its own read of the same frame before augmentation, held fixed: what an augmentation adds
    to the look (a fan of light, a band) should not move where the dolphin is read."""
    with torch.no_grad():
        plain = student.decode_state(student.encode(plain_images)[0])
    parts.consistency = F.mse_loss(parts.prediction[:, :PSI], plain[:, :PSI])
    parts.total = parts.total + weight * parts.consistency
    return parts


# ---------------------------------------------------------------- checkpoints


def make_checkpoint(
    model: CMVAE, beta: float, epoch: int, val_loss: float, metrics: dict[str, float], **extra: Any
) -> dict[str, Any]:
    """The checkpoint dict: plain types and CPU tensors only, so ``torch.load(weights_only=True)`` reads it.

    ``epoch`` counts completed epochs (1 after the first); ``extra`` carries
    what only a resumable checkpoint needs (optimiser state, RNG state).
    """
    state_dict = {name: tensor.detach().cpu() for name, tensor in model.state_dict().items()}
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": {
            "n_z": model.n_z,
            "beta": float(beta),
            "input_norm": model.input_norm,
            "mask_head": model.mask_head is not None,
            "labels": list(model.labels),
            "locate": model.locates,
            "track": model.tracks,
            "mirror_average": model.mirror_averages,
            "prior_distance": model.prior_distance,
            "circular_psi": model.circular_psi,
        },
        "state_dict": state_dict,
        "epoch": int(epoch),
        "val_loss": float(val_loss),
        "metrics": {key: float(value) for key, value in metrics.items()},
        **extra,
    }


def resolve_device(name: str) -> torch.device:
    """The torch device ``--device`` names ("auto": CUDA where torch sees it, else the CPU); one that torch does
    not know, or CUDA where torch sees none, is refused by name."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"--device {name!r} is not a torch device (cpu, cuda, cuda:1, mps, ...)") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name!r} asked for, but torch sees no CUDA device (use --device cpu)")
    return device


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load and check a checkpoint dict (safe unpickling); a clear error says what is wrong with it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"CMVAE checkpoint {path} does not exist (make one with `swimm train-encoder`)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch has no one error for a file not its own (unpickling, zip, index, ...)
        raise ValueError(
            f"{path} is not a {CHECKPOINT_FORMAT} checkpoint: torch cannot read it ({type(exc).__name__})"
        ) from exc
    if isinstance(checkpoint, dict) and checkpoint.get("format") == DETECTOR_FORMAT:
        raise ValueError(
            f"{path} is a pod detector, not a CMVAE: `swimm encoder` and `--encoder-checkpoint` open one, "
            "but this command reads CMVAEs only"
        )
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a {CHECKPOINT_FORMAT} checkpoint")
    if checkpoint.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {checkpoint.get('version')!r}, expected {CHECKPOINT_VERSION}")
    return checkpoint


def refuse_distance_prior(path: str | Path, where: str) -> None:
    """A tracking CMVAE whose prior holds the target's distance has no exported form yet (the ONNX file's prior is an
    azimuth): ``where`` refuses one by name."""
    if read_checkpoint(path)["config"].get("prior_distance", False):
        raise ValueError(
            f"{path} is a tracking CMVAE whose prior holds the target's distance (--prior-distance): "
            f"{where} carries an azimuth prior only so far; `swimm eval` and `swimm encoder` run it"
        )


def load_model(path: str | Path, device: torch.device | str = "cpu") -> tuple[CMVAE, dict[str, Any]]:
    """A CMVAE in eval mode, channels_last, on ``device``, with the checkpoint dict it came from."""
    checkpoint = read_checkpoint(path)
    config = checkpoint["config"]
    model = CMVAE(
        n_z=int(config["n_z"]),
        input_norm=config.get("input_norm", "none"),
        mask_head=config.get("mask_head", False),
        labels=check_label_names(config.get("labels", LABEL_NAMES), str(path)),  # older checkpoints: planar
        locate=config.get("locate", False),
        track=config.get("track", False),
        mirror_average=config.get("mirror_average", False),
        prior_distance=config.get("prior_distance", False),
        circular_psi=config.get("circular_psi", False),
    )
    model.load_state_dict(checkpoint["state_dict"])
    model.to(device=device, memory_format=torch.channels_last).eval()
    return model, checkpoint
