"""Selection diagnostic: one reading from the pod detector, the rest from the CMVAE. Runs `swimm eval` (the suite,
usually) with the CMVAE's latent in which the azimuth dimension (`--take azimuth`, the detector says where and the
CMVAE how far) or the distance dimension (`--take distance`) holds the pod detector's tracked reading wherever its
tracker has a target (the CMVAE's own reading elsewhere), so a policy trained on that CMVAE flies on it unchanged.

    MUJOCO_GL=egl python docs/encoder/selection/fused_suite.py CMVAE DETECTOR --take azimuth -- eval --suite ... \
        --encoder-checkpoint CMVAE ...

The latent's value is the one the CMVAE's own state decoder maps to the detector's reading (its inverse,
tabulated: the decoder is monotonic, which is checked). Not a shipped encoder: the suite's machinery opens
encoders by file, so the CMVAE's file is swapped for this one in the processes' loaders (in process only).
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
from services.pod_tracker import STATE_SIZE

#: The reading taken from the detector: its index in the tracker's (distance, azimuth) and in the CMVAE's latent.
TAKEN = {"distance": 0, "azimuth": 1}


class DetectorReading:
    """A CMVAE's encoder whose distance or azimuth latent is set from the pod detector's tracker; it carries the
    tracker's state as a tracking encoder's prior."""

    tracks = True
    prior_shape = (STATE_SIZE,)

    def __init__(self, cmvae: str, detector: str, take: str) -> None:
        self.column = TAKEN[take]
        self.cmvae = inference.LatentEncoder(cmvae)
        self.pod = PodEncoder(detector)
        self.n_z, self.labels = self.cmvae.n_z, self.cmvae.labels
        grid = np.linspace(-6.0, 6.0, 6001, dtype=np.float32)
        latents = np.zeros((len(grid), self.n_z), np.float32)
        latents[:, self.column] = grid
        read = self.cmvae.decode_state(latents)[self.column]
        if not (np.all(np.diff(read) > 0) or np.all(np.diff(read) < 0)):
            raise ValueError(f"{cmvae}'s {take} decoder is not monotonic over [-6, 6]: no inverse to tabulate")
        order = np.argsort(read)
        self._read, self._z = read[order], grid[order]
        self.replaced = self.frames = 0

    def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        mu, logvar = self.cmvae.encode(images)
        detections = self.pod.detect(images)
        states = np.zeros((len(images), STATE_SIZE), np.float32)
        mu = mu.copy()
        for row, frame in enumerate(detections):
            prior = None if priors is None or not np.any(priors[row]) else priors[row]
            states[row], reading = self.pod.tracker.update(prior, frame)
            if reading is not None:
                mu[row, self.column] = np.interp(reading[self.column], self._read, self._z)
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
    parser.add_argument("--take", choices=sorted(TAKEN), default="azimuth", help="the reading the detector gives")
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])  # after "--": the swimm command line
    fused = DetectorReading(args.cmvae, args.detector, args.take)
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
