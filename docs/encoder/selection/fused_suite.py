"""Selection diagnostic: one reading from the pod detector, the rest from the CMVAE. Runs `swimm eval` (the suite,
usually) with the CMVAE's latent in which the azimuth dimension (`--take azimuth`, the detector says where and the
CMVAE how far), the distance dimension (`--take distance`) or both (`--take both`) hold the pod detector's tracked
reading wherever its tracker has a target whose peak this frame scores at least `--min-score` (the CMVAE's own
reading elsewhere), so a policy trained on that CMVAE flies on it unchanged.

    MUJOCO_GL=egl python docs/encoder/selection/fused_suite.py CMVAE DETECTOR --take azimuth -- eval --suite ... \
        --encoder-checkpoint CMVAE ...

The latent's value is the one the CMVAE's own state decoder maps to the detector's reading (its inverse,
tabulated over the decoder's monotonic span through 0, which must reach from -2 to 2). Not a shipped encoder: the
suite's machinery opens encoders by file, so the CMVAE's file is swapped for this one in the processes' loaders (in
process only).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

import encoder_service.inference as inference
import eval_service.suite as suite
import learner_service.envs as envs
import learner_service.registry as registry
from encoder_service.pod_encoder import PodEncoder
from services.detections import Detections
from services.pod_tracker import AZIMUTH, FIELDS, MAX_TRACKS, MISSES, STATE_SIZE, TARGET

#: The readings taken from the detector: their indices in the tracker's (distance, azimuth) and in the CMVAE's latent.
TAKEN = {"distance": (0,), "azimuth": (1,), "both": (0, 1)}


def monotonic_span(values: np.ndarray) -> tuple[int, int]:
    """The first and last index of the longest strictly monotonic run of ``values`` through its middle."""
    steps = np.sign(np.diff(values))
    middle = len(steps) // 2
    low = high = middle
    while low > 0 and steps[low - 1] == steps[middle] != 0:
        low -= 1
    while high < len(steps) - 1 and steps[high + 1] == steps[middle] != 0:
        high += 1
    return low, high + 1


def target_score(state: np.ndarray, frame: Detections) -> float:
    """The score of the peak the target's track matched this frame (the one nearest its azimuth), 0 if none."""
    tracks = state.reshape(MAX_TRACKS, len(FIELDS))
    target = np.nonzero(tracks[:, TARGET] > 0)[0]
    if len(target) == 0 or tracks[target[0], MISSES] > 0 or len(frame) == 0:
        return 0.0
    return float(frame.score[np.argmin(np.abs(frame.azimuth - tracks[target[0], AZIMUTH]))])


class DetectorReading:
    """A CMVAE's encoder whose distance or azimuth latent is set from the pod detector's tracker; it carries the
    tracker's state as a tracking encoder's prior."""

    tracks = True
    prior_shape = (STATE_SIZE,)

    def __init__(self, cmvae: str, detector: str, take: str, min_score: float = 0.0) -> None:
        self.columns, self.min_score = TAKEN[take], min_score
        self.cmvae = inference.LatentEncoder(cmvae)
        self.pod = PodEncoder(detector)
        self.n_z, self.labels = self.cmvae.n_z, self.cmvae.labels
        self._inverse = {column: self._tabulate(column) for column in self.columns}
        self.replaced = self.frames = 0

    def _tabulate(self, column: int) -> tuple[np.ndarray, np.ndarray]:
        """The CMVAE's decoder of one reading as (readings, latents), sorted, for :func:`np.interp`."""
        grid = np.linspace(-6.0, 6.0, 6001, dtype=np.float32)
        latents = np.zeros((len(grid), self.n_z), np.float32)
        latents[:, column] = grid
        read = self.cmvae.decode_state(latents)[column]
        low, high = monotonic_span(read)
        if grid[low] > -2.0 or grid[high] < 2.0:
            raise ValueError(f"the CMVAE's decoder {column} is monotonic over [{grid[low]:.2f}, {grid[high]:.2f}] "
                             "only, not over [-2, 2]: no inverse to tabulate")  # fmt: skip
        order = np.argsort(read[low : high + 1])
        return read[low : high + 1][order], grid[low : high + 1][order]

    def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        mu, logvar = self.cmvae.encode(images)
        detections = self.pod.detect(images)
        states = np.zeros((len(images), STATE_SIZE), np.float32)
        mu = mu.copy()
        for row, frame in enumerate(detections):
            prior = None if priors is None or not np.any(priors[row]) else priors[row]
            states[row], reading = self.pod.tracker.update(prior, frame)
            if reading is not None and target_score(states[row], frame) >= self.min_score:
                for column, (read, latent) in self._inverse.items():
                    mu[row, column] = np.interp(reading[column], read, latent)
                self.replaced += 1
        self.frames += len(images)
        return mu, logvar, states

    def encode(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        return self.track(images, priors)[:2]

    def decode_state(self, mu: np.ndarray) -> tuple[np.ndarray, ...]:
        return self.cmvae.decode_state(mu)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cmvae")
    parser.add_argument("detector")
    parser.add_argument("--take", choices=sorted(TAKEN), default="azimuth", help="the readings the detector gives")
    parser.add_argument("--min-score", type=float, default=0.0,
                        help="take them only where the target's peak scores at least this")  # fmt: skip
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])  # after "--": the swimm command line
    fused = DetectorReading(args.cmvae, args.detector, args.take, args.min_score)
    opened = inference.open_encoder

    def open_encoder(checkpoint=None, *rest, **options):  # the CMVAE's file opens the fused encoder
        return fused if str(checkpoint) == args.cmvae else opened(checkpoint, *rest, **options)

    envs.open_encoder = registry.open_encoder = suite.open_encoder = open_encoder
    from swimm.cli import main as swimm

    code = swimm(argv[split + 1 :])
    print(f"{args.take} from the detector on {fused.replaced} of {fused.frames} frames")
    return code


if __name__ == "__main__":
    sys.exit(main())
