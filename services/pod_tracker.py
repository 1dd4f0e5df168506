"""Which detection is the target: every dolphin tracked across frames, the target one of the tracks.

The detector (encoder_service.pod_detector) says where the dolphins are in one frame; identity lives across frames.
Each track holds a dolphin's azimuth and log distance with their rates (an alpha-beta filter), and detections join
tracks by the nearest gated match in both, the cheapest pairs first. The target is the track the first frame's
dolphin nearest the image centre started (the engagement rule, docs/physics.md, "Pods"), among the peaks at least
half as strong as the frame's strongest.

Each track also keeps the mean look its detections read (how light the animal shows against the water,
services.detections.pixel_looks), and a detection whose look lies far from a track's, once that track has read
enough of them, does not join it: look-alikes that overlap for seconds are told apart by their grey when their
motion no longer can.

Distance is what tells a companion passing in front from the target: the one in front is nearer. While the target
has no detection and a nearer dolphin covers where it was, the target is *behind* it: its azimuth is held within
the disc of the one in front and its distance stays put, so when the two part the target's track
takes the farther dolphin again.

The whole state is one float vector (:data:`STATE_SIZE`), so the loop can carry it from frame to frame as it
carries a tracking encoder's prior, and an encoder that reads frames keeps none.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.detections import Detections, read_peaks
from services.geometry import OPT_D
from services.identity import DOLPHIN_RADIUS_M

FIELDS = ("alive", "target", "azimuth", "log_d", "rate", "log_d_rate", "misses", "behind", "look", "look_reads")
ALIVE, TARGET, AZIMUTH, LOG_D, RATE, LOG_D_RATE, MISSES, BEHIND, LOOK, LOOK_READS = range(len(FIELDS))
MAX_TRACKS = 8
STATE_SIZE = MAX_TRACKS * len(FIELDS)
NOT_MATCHED = math.inf
PRIORITY_STEP = 100.0  # above any gated cost: a cascade level
#: The reading before any dolphin is engaged: the task's optimum distance, dead ahead, so the rover holds still.
UNSEEN = (OPT_D, 0.0)


@dataclass(frozen=True)
class TrackerParams:
    azimuth_sigma_deg: float = 1.5  # a matched detection's spread about its track's prediction
    azimuth_sigma_growth_deg: float = 0.1  # per frame without a detection
    max_azimuth_sigma_deg: float = 15.0
    behind_azimuth_sigma_deg: float = 5.0  # a target behind another comes out beside it
    log_d_sigma: float = 0.2  # about 20% in distance: a pod's dolphins lie close in distance, the reads less so
    log_d_sigma_growth: float = 0.01  # per frame without a detection, unless the track is behind another
    max_log_d_sigma: float = 0.35
    gate: float = 9.0  # the largest squared normalised distance a match may have (3 sigma)
    azimuth_gain: float = 0.6
    rate_gain: float = 0.1
    log_d_gain: float = 0.25
    log_d_rate_gain: float = 0.01
    rate_decay: float = 0.9  # per frame without a detection
    companion_misses: int = 10  # a companion's track ends after this many frames without a detection
    reacquire_after: int = 20  # frames a target may go unseen, behind no one, before another seen one takes over
    reacquire_azimuth_sigma_deg: float = 10.0
    nearer: float = 0.92  # a dolphin covers the target when nearer than this share of its distance...
    cover_margin_deg: float = 1.0  # ...and its disc, widened by this, holds the target's centre
    engage_score_share: float = 0.5  # at engagement, a peak weaker than this share of the strongest is no candidate
    look_sigma: float = 12.0  # the spread (grey levels) a match allows a look about its track's mean (0: the cue off)
    look_min_reads: int = 10  # a track's mean look counts once it has read this many
    look_memory: int = 1000  # the mean weighs the last reads about this many frames long (20 s)


class PodTracker:
    """``update(state, detections) -> (next state, (distance m, azimuth deg) of the target or None)``."""

    def __init__(self, params: TrackerParams | None = None) -> None:
        self.params = params or TrackerParams()

    def update(
        self, state: np.ndarray | None, frame: Detections, engage_deg: float = 0.0
    ) -> tuple[np.ndarray, tuple[float, float] | None]:
        """The next state and the target's (distance, azimuth), None while no target is engaged; ``engage_deg`` is
        the azimuth the engagement looks nearest to (the image centre unless an operator points elsewhere)."""
        blank = np.zeros(STATE_SIZE)
        tracks = np.array(blank if state is None else state, dtype=float).reshape(MAX_TRACKS, len(FIELDS))
        alive = tracks[:, ALIVE] > 0
        tracks[alive, AZIMUTH] += tracks[alive, RATE]
        tracks[alive, LOG_D] += tracks[alive, LOG_D_RATE]
        log_d = np.log(np.maximum(frame.distance, 0.1))
        track_of = {detection: track for track, detection in self._match(tracks, frame.azimuth, log_d, frame.look)}
        for detection, track in track_of.items():
            self._correct(tracks[track], frame.azimuth[detection], log_d[detection], frame.look[detection])
        for track in np.nonzero(alive)[0]:
            if track not in track_of.values():
                self._coast(tracks, track, frame, log_d, track_of)
        tracks[(tracks[:, TARGET] == 0) & (tracks[:, MISSES] > self.params.companion_misses)] = 0.0
        engage = not np.any(tracks[:, TARGET] > 0)
        self._start_tracks(tracks, frame, log_d, set(track_of), engage, engage_deg)
        self._reacquire(tracks)
        target = np.nonzero(tracks[:, TARGET] > 0)[0]
        reading = None if len(target) == 0 else (math.exp(tracks[target[0], LOG_D]), tracks[target[0], AZIMUTH])
        return tracks.reshape(-1).astype(np.float32), reading

    def _reacquire(self, tracks: np.ndarray) -> None:
        """A target unseen too long, and behind no one, is lost: the dolphin seen now likeliest to be it (nearest
        its last azimuth and distance, loosely) becomes the target, so the rover keeps a dolphin in view."""
        p = self.params
        targets = np.nonzero(tracks[:, TARGET] > 0)[0]
        if len(targets) == 0:
            return
        target = targets[0]
        if tracks[target, MISSES] <= p.reacquire_after or tracks[target, BEHIND] > 0:
            return
        seen = np.nonzero((tracks[:, ALIVE] > 0) & (tracks[:, MISSES] == 0))[0]
        if len(seen) == 0:
            return
        cost = _apart(tracks[seen], tracks[target, AZIMUTH], tracks[target, LOG_D],
                      p.reacquire_azimuth_sigma_deg, p.max_log_d_sigma)  # fmt: skip
        if tracks[target, LOOK_READS] >= p.look_min_reads:  # the look it had, where the seen ones' are known
            cost += self._unlike(tracks[seen], tracks[target, LOOK])
        chosen = seen[int(np.argmin(cost))]
        tracks[target] = 0.0
        tracks[chosen, TARGET] = 1.0

    def _sigmas(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each track's match spreads: wider the longer it goes unseen, except behind another, which bounds it."""
        p = self.params
        misses = np.where(tracks[:, BEHIND] > 0, 0.0, tracks[:, MISSES])
        azimuth = np.minimum(p.azimuth_sigma_deg + p.azimuth_sigma_growth_deg * misses, p.max_azimuth_sigma_deg)
        azimuth = np.where(tracks[:, BEHIND] > 0, p.behind_azimuth_sigma_deg, azimuth)
        return azimuth, np.minimum(p.log_d_sigma + p.log_d_sigma_growth * misses, p.max_log_d_sigma)

    def _unlike(self, tracks: np.ndarray, look: np.ndarray) -> np.ndarray:
        """Squared normalised gap between tracks' mean looks and detections' looks, broadcast; 0 where either is
        unknown (a track with too few reads, a detection read without its frame)."""
        p = self.params
        if p.look_sigma <= 0:
            return np.zeros(np.broadcast_shapes(tracks.shape[:-1], np.shape(look)))
        gap = ((tracks[..., LOOK] - look) / p.look_sigma) ** 2
        known = (tracks[..., LOOK_READS] >= p.look_min_reads) & np.isfinite(look)
        return np.where(known, gap, 0.0)

    def _match(
        self, tracks: np.ndarray, azimuth: np.ndarray, log_d: np.ndarray, look: np.ndarray
    ) -> list[tuple[int, int]]:
        """Gated (track, detection) pairs, cheapest first, each track and detection at most once."""
        alive = np.nonzero(tracks[:, ALIVE] > 0)[0]
        if len(alive) == 0 or len(azimuth) == 0:
            return []
        sigma_azimuth, sigma_log_d = self._sigmas(tracks[alive])
        cost = _apart(tracks[alive, None], azimuth[None], log_d[None], sigma_azimuth[:, None], sigma_log_d[:, None])
        looks = self._unlike(tracks[alive, None], look[None])
        cost[(cost > self.params.gate) | (looks > self.params.gate)] = NOT_MATCHED
        cost += looks
        # A matching cascade: tracks seen more recently choose first, so a coasting target never steals the
        # detection of a companion seen all along (the one now in front of it).
        cost += PRIORITY_STEP * tracks[alive, MISSES, None]
        pairs = []
        while np.isfinite(cost).any():
            row, column = np.unravel_index(np.argmin(cost), cost.shape)
            pairs.append((int(alive[row]), int(column)))
            cost[row, :] = NOT_MATCHED
            cost[:, column] = NOT_MATCHED
        return pairs

    def _correct(self, track: np.ndarray, azimuth: float, log_d: float, look: float) -> None:
        p = self.params
        if np.isfinite(look):
            track[LOOK] += (look - track[LOOK]) / min(track[LOOK_READS] + 1, p.look_memory)
            track[LOOK_READS] += 1
        residual = azimuth - track[AZIMUTH]
        track[AZIMUTH] += p.azimuth_gain * residual
        track[RATE] += p.rate_gain * residual
        residual = log_d - track[LOG_D]
        track[LOG_D] += p.log_d_gain * residual
        track[LOG_D_RATE] += p.log_d_rate_gain * residual
        track[MISSES] = track[BEHIND] = 0.0

    def _coast(
        self, tracks: np.ndarray, index: int, frame: Detections, log_d: np.ndarray, track_of: dict[int, int]
    ) -> None:
        """A track without a detection keeps its prediction; the target's goes behind a nearer dolphin covering it
        (were it outside that one's disc, the frame would show it), and nears or recedes as that one does (the
        rover closing on both)."""
        track = tracks[index]
        track[MISSES] += 1
        track[RATE] *= self.params.rate_decay
        track[LOG_D_RATE] *= self.params.rate_decay
        if track[TARGET] > 0:
            cover = self._covering(track, frame, log_d)
            track[BEHIND] = float(cover is not None)
            if cover is not None:  # hidden somewhere behind the nearer one's disc: held within it
                extent = float(_angular_radius_deg(frame.distance[cover]))
                low, high = frame.azimuth[cover] - extent, frame.azimuth[cover] + extent
                track[AZIMUTH] = min(max(track[AZIMUTH], low), high)
                if cover in track_of:
                    track[LOG_D_RATE] = tracks[track_of[cover], LOG_D_RATE]

    def _covering(self, track: np.ndarray, frame: Detections, log_d: np.ndarray) -> int | None:
        """The nearest-in-azimuth detection that is nearer than the track and whose disc overlaps its own."""
        p = self.params
        reach = _angular_radius_deg(frame.distance) + p.cover_margin_deg  # its centre behind the nearer one's disc
        apart = np.abs(frame.azimuth - track[AZIMUTH])
        covering = (log_d < track[LOG_D] + math.log(p.nearer)) & (apart < reach)
        if not covering.any():
            return None
        return int(np.argmin(np.where(covering, apart, np.inf)))

    def _start_tracks(
        self, tracks: np.ndarray, frame: Detections, log_d: np.ndarray, used: set[int], engage: bool, engage_deg: float
    ) -> None:
        """New tracks for detections no track took; at engagement the one nearest ``engage_deg`` on the horizon (the
        image centre by default) is the target."""
        fresh = [j for j in range(len(frame)) if j not in used and not self._explained(tracks, frame, log_d, j)]
        if engage and fresh:
            # a stray peak (marine snow, a shaft's edge) near the centre must not outbid a dolphin seen plainly
            weak = frame.score[fresh] < self.params.engage_score_share * frame.score[fresh].max()
            off_axis = np.where(weak, np.inf, np.hypot(frame.azimuth[fresh] - engage_deg, frame.elevation[fresh]))
            fresh.insert(0, fresh.pop(int(np.argmin(off_axis))))
        for order, detection in enumerate(fresh):
            free = np.nonzero(tracks[:, ALIVE] == 0)[0]
            if len(free) == 0:
                return
            track = tracks[free[0]]
            track[:] = 0.0
            track[ALIVE] = 1.0
            track[TARGET] = float(engage and order == 0)
            track[AZIMUTH], track[LOG_D] = frame.azimuth[detection], log_d[detection]
            if np.isfinite(frame.look[detection]):
                track[LOOK], track[LOOK_READS] = frame.look[detection], 1.0

    def _explained(self, tracks: np.ndarray, frame: Detections, log_d: np.ndarray, detection: int) -> bool:
        """Whether a detection lies within a live track's gate: a second peak on a dolphin already tracked."""
        alive = tracks[:, ALIVE] > 0
        if not alive.any():
            return False
        sigma_azimuth, sigma_log_d = self._sigmas(tracks[alive])
        cost = _apart(tracks[alive], frame.azimuth[detection], log_d[detection], sigma_azimuth, sigma_log_d)
        return bool((cost < self.params.gate).any())


class TargetReader:
    """One camera's target, frame by frame: a detector's heat and regression (any runtime: ``detect(frame) -> (heat
    (1, G, G) in (0, 1), regression (1, 3, G, G))``) read as peaks and tracked; for `swimm pilot` and the export's
    check, which run an exported detector without torch."""

    def __init__(
        self,
        detect: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
        threshold: float,
        stride: int,
        size: int,
        params: TrackerParams | None = None,
    ) -> None:
        self.detect, self.threshold, self.stride, self.size = detect, threshold, stride, size
        self.tracker = PodTracker(params)
        self.reset()

    def reset(self, engage_deg: float = 0.0) -> None:
        """Track afresh: the next frame engages the dolphin nearest ``engage_deg`` (degrees, + = left)."""
        self.state: np.ndarray | None = None
        self.engage_deg = engage_deg

    def read(self, frame: np.ndarray) -> tuple[float, float]:
        """The target's (distance m, azimuth deg) in one uint8 frame (H, W, 3); :data:`UNSEEN` before engagement."""
        heat, regression = self.detect(frame[None])
        (detections,) = read_peaks(heat, regression, self.threshold, self.size, self.stride, frame[None])
        self.state, reading = self.tracker.update(self.state, detections, self.engage_deg)
        return reading or UNSEEN


def _angular_radius_deg(distance: np.ndarray | float) -> np.ndarray:
    return np.degrees(np.arcsin(np.clip(DOLPHIN_RADIUS_M / np.maximum(distance, 1e-6), 0.0, 1.0)))


def _apart(tracks: np.ndarray, azimuth, log_d, sigma_azimuth, sigma_log_d) -> np.ndarray:
    """Squared normalised distance of ``tracks`` (rows of the state) from (azimuth, log distance), broadcast."""
    return ((tracks[..., AZIMUTH] - azimuth) / sigma_azimuth) ** 2 + ((tracks[..., LOG_D] - log_d) / sigma_log_d) ** 2
