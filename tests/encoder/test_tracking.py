"""The tracking CMVAE: an encoder that reads, beside each frame, where its target was last seen (pods)."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.data import CMVAEDataset, DatasetUnion
from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import (
    CMVAE,
    ENGAGEMENT_SHARE,
    EVALUATION_PRIORS_SEED,
    encoder_input,
    make_checkpoint,
    prior_map,
    training_priors,
    with_prior,
)
from encoder_service.train import load_init_weights, mirror_batch, run
from services.identity import TARGET
from tests.encoder.cmvae_testdata import write_dataset as write_lone_dataset
from tests.encoder.pod_testdata import render_pod_dataset
from tests.encoder.quick_training import GENERAL, quick_settings, started_from_general


@pytest.fixture(scope="module")
def pod(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small dataset of a pod of 3, with the target's masks."""
    return render_pod_dataset(tmp_path_factory.mktemp("tracking") / "pod", count=96, shard_size=48)


_settings = partial(quick_settings, track=True, input_norm="channel")


@pytest.fixture(scope="module")
def followed(pod: Path) -> np.ndarray:
    """Each sample of the pod dataset placed again by the sim (its own seed), and the dolphin the sim's
    rover follows there (services.identity: in view, not hidden, nearest the image centre), from MuJoCo's camera."""
    from sim_service.dataset import SamplingRanges, sample_pose
    from sim_service.settings import DolphinSettings, WorldSettings
    from sim_service.world import World

    meta = CMVAEDataset(pod).meta
    world = World(WorldSettings(render=False, dolphin=DolphinSettings(pod_size=meta["pod"]["size"])))
    try:
        followed = []
        for row in range(meta["count"]):
            rng = np.random.default_rng([meta["seed"], row])
            telemetry, _ = sample_pose(world, rng, SamplingRanges(), meta["pod"]["sight_share"])
            followed.append(telemetry.followed)
    finally:
        world.close()
    return np.array(followed)


def test_a_pod_dataset_marks_the_targets_the_sim_would_engage_on(pod: Path, followed: np.ndarray) -> None:
    """The loader's ``centred`` (from the stored poses) is the sim's own "followed is the target"; some are not."""
    batch = CMVAEDataset(pod).read(np.arange(96))
    np.testing.assert_array_equal(batch.centred, followed == TARGET)
    assert 10 <= batch.centred.sum() <= 86  # both kinds, so the priors below are tested on each
    flipped = mirror_batch(batch, np.arange(96) % 2 == 0)
    np.testing.assert_array_equal(flipped.centred, batch.centred)


def test_engagement_priors_go_to_a_share_of_the_centred_targets_only(pod: Path, followed: np.ndarray) -> None:
    batch = CMVAEDataset(pod).read(np.arange(96))
    rng = np.random.default_rng(7)
    draws = np.stack([training_priors(batch.labels[:, 1], batch.centred, rng) for _ in range(200)])
    engaged = draws == 0.0
    assert not engaged[:, ~batch.centred].any()
    assert not engaged[:, followed > TARGET].any()  # a companion nearer the centre: never the engagement prior
    assert abs(engaged[:, batch.centred].mean() - ENGAGEMENT_SHARE) < 0.02
    misses = (draws - batch.labels[:, 1])[~engaged]
    assert 5.0 < np.sqrt(np.mean(misses**2)) < 10.0  # the others keep the jitter about the true azimuth

    model = CMVAE(input_norm="channel", track=True)
    evaluated = [
        encoder_input(model, batch.images, batch.labels, "cpu", np.random.default_rng(EVALUATION_PRIORS_SEED),
                      batch.centred)[:, 3, 0]
        for _ in range(2)
    ]  # fmt: skip
    torch.testing.assert_close(evaluated[0], evaluated[1], rtol=0.0, atol=0.0)  # validation reads the same priors
    centre = prior_map(torch.zeros(1))[0, 0, 0]
    at_centre = (evaluated[0] == centre).all(dim=1).numpy()
    assert at_centre.any() and not at_centre[~batch.centred].any()


def test_a_lone_dolphins_targets_are_always_centred(pod: Path, tmp_path: Path) -> None:
    lone = CMVAEDataset(write_lone_dataset(tmp_path / "lone", count=20, seed=1, shard_size=8))
    assert lone.pod_size == 1 and lone.read(np.arange(20)).centred.all()
    both = DatasetUnion([lone, CMVAEDataset(pod)]).read(np.arange(116))
    np.testing.assert_array_equal(both.centred[20:], CMVAEDataset(pod).read(np.arange(96)).centred)
    assert both.centred[:20].all()
    priors = training_priors(np.full(2000, 30.0), None, np.random.default_rng(3))
    assert abs((priors == 0.0).mean() - ENGAGEMENT_SHARE) < 0.03  # a lone dolphin 30 deg off the centre too


def test_the_prior_stripe_sits_where_the_camera_shows_the_target(pod: Path) -> None:
    """The stripe's brightest column against the target's pixels (MuJoCo's segmentation) in rendered pod frames."""
    masks = np.load(pod / "shard-00000.masks.npy")
    azimuths = np.load(pod / "shard-00000.labels.npy")[:, 1]
    stripes = prior_map(torch.from_numpy(azimuths)).numpy()[:, 0, 0]  # one row: every row is the same
    assert stripes.min() >= -1.0 and stripes.max() <= 1.0
    seen = masks.sum(axis=(1, 2)) >= 10
    assert seen.sum() >= 20
    target_columns = np.array([np.nonzero(mask)[1].mean() for mask in masks[seen]])
    stripe_columns = stripes[seen].argmax(axis=1)
    assert np.median(np.abs(target_columns - stripe_columns)) < 2.0  # pixels of 64


def test_a_tracking_encoder_starts_as_the_model_it_is_initialised_from(pod: Path) -> None:
    """The prior reaches the first convolution through zero weights at first: the latents are the checkpoint's."""
    started, general, frames = started_from_general(pod, track=True)
    with torch.no_grad():
        tracked = started.encode(with_prior(frames, torch.linspace(-20, 20, 8)))
        torch.testing.assert_close(tracked, general.encode(frames), rtol=1e-5, atol=1e-5)


def test_a_trained_tracker_reads_its_prior_in_torch_onnx_and_export(pod: Path, tmp_path: Path) -> None:
    run(_settings(pod, tmp_path / "run", epochs=2, lr=1e-3, batch_size=16, init=str(GENERAL)))
    checkpoint = tmp_path / "run" / "last.pt"
    assert torch.load(checkpoint, weights_only=True)["config"]["track"] is True
    frames = np.load(pod / "shard-00001.images.npy")[:6]
    priors = np.array([-15.0, -5.0, 0.0, 3.0, 10.0, 20.0], dtype=np.float32)
    encoder = LatentEncoder(checkpoint)
    assert encoder.tracks and not LatentEncoder(GENERAL).tracks
    torch_mu, _ = encoder.encode(frames, priors)
    onnx_mu, _, onnx_next_priors = LatentEncoder(checkpoint, engine="onnx").track(frames, priors)
    # float32: the engines' stripes (tan, exp) differ in the last bits, which a prior-reading first layer amplifies
    np.testing.assert_allclose(onnx_mu, torch_mu, rtol=1e-4, atol=3e-4)
    assert np.abs(encoder.encode(frames, -priors)[0] - torch_mu).max() > 1e-4  # the prior is read
    centred, _ = encoder.encode(frames)  # no priors: the image centre, the engagement rule
    np.testing.assert_array_equal(centred, encoder.encode(frames, np.zeros(6, np.float32))[0])

    _, _, next_priors = encoder.track(frames, priors)
    np.testing.assert_allclose(next_priors, encoder.decode_state(torch_mu)[1], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(onnx_next_priors, next_priors, atol=1e-2)
    with pytest.raises(ValueError, match="does not track"):
        LatentEncoder(GENERAL).track(frames, priors)

    exported = export_checkpoint(checkpoint, tmp_path / "exported.pt")
    exported_mu, _ = LatentEncoder(exported).encode(frames, priors)
    np.testing.assert_allclose(exported_mu, torch_mu, atol=2e-2)  # float16 weights


def test_refusals_name_what_is_wrong(pod: Path, tmp_path: Path) -> None:
    encoder = LatentEncoder(GENERAL)
    frames = np.load(pod / "shard-00000.images.npy")[:2]
    for bad in (np.zeros(3), np.array([0.0, np.nan]), np.zeros((2, 1))):
        with pytest.raises(ValueError, match="priors must be 2 finite azimuths"):
            encoder.encode(frames, bad)
    run(_settings(pod, tmp_path / "plain", track=False))
    with pytest.raises(ValueError, match="track=False: resume it so"):
        run(_settings(pod, tmp_path / "plain", epochs=2, resume=True))


class _Recording(LatentEncoder):
    """The real encoder, noting the priors the env hands it."""

    def __init__(self, checkpoint: Path) -> None:
        super().__init__(checkpoint)
        self.seen: list[np.ndarray] = []

    def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        engagement = np.zeros(self.prior_shape, np.float32)  # None: the engagement prior, the centre (and 0 m)
        self.seen.append(engagement if priors is None else priors[0])
        return super().track(images, priors)


@pytest.mark.parametrize("prior_distance", [False, True])
def test_the_in_process_env_hands_each_frame_the_prior_its_last_latent_decoded_to(
    tmp_path: Path, prior_distance: bool
) -> None:
    from learner_service.inprocess_env import TrackingEnv
    from learner_service.task import TaskSettings

    model = CMVAE(input_norm="channel", track=True, prior_distance=prior_distance)
    load_init_weights(model, str(GENERAL), n_z=10)
    torch.save(make_checkpoint(model.eval(), 8.0, 1, 0.0, {}), tmp_path / "tracking.pt")
    encoder = _Recording(tmp_path / "tracking.pt")
    env = TrackingEnv(TaskSettings(obs="cmvae", use_latent_mean=True), base_seed=5, encoder=encoder)
    latents = [env.reset()[0]]
    latents += [env.step(np.zeros(env.action_space.shape, np.float32))[0] for _ in range(3)]
    env.reset()
    env.close()
    assert not encoder.seen[0].any() and not encoder.seen[4].any()  # each episode starts at the image centre
    mus = np.stack([latent[: encoder.n_z] for latent in latents[:3]])
    distance, theta, *_ = encoder.decode_state(mus)
    read = np.stack([theta, distance], axis=1) if prior_distance else theta
    np.testing.assert_allclose(np.stack(encoder.seen[1:4]), read, rtol=1e-5, atol=1e-4)


def test_a_distance_prior_adds_the_targets_distance_and_leaves_the_azimuths_as_they_were() -> None:
    azimuths, distances = np.linspace(-30.0, 30.0, 4000), np.linspace(3.0, 9.0, 4000)
    alone = training_priors(azimuths, None, np.random.default_rng(8))
    both = training_priors(azimuths, None, np.random.default_rng(8), distances)
    assert both.shape == (4000, 2) and both.dtype == np.float32
    np.testing.assert_array_equal(both[:, 0], alone)  # drawn after the azimuths: those do not move
    engaged = both[:, 0] == 0.0
    assert (both[engaged, 1] == 0.0).all() and (both[~engaged, 1] >= 2.0).all()  # 0 m: not yet seen
    misses = both[~engaged, 1] / distances[~engaged] - 1.0
    assert 0.1 < misses.std() < 0.2 and abs(np.median(misses)) < 0.01
    planes = with_prior(torch.zeros(4, 3, 64, 64), torch.tensor([[0.0, 2.0], [0.0, 6.0], [0.0, 10.0], [0.0, 0.0]]))
    assert planes.shape == (4, 5, 64, 64)
    np.testing.assert_allclose(planes[:, 4].amin(dim=(1, 2)), [-1.0, 0.0, 1.0, -1.5])  # the d label's scale
    np.testing.assert_array_equal(planes[:, 4].amax(dim=(1, 2)), planes[:, 4].amin(dim=(1, 2)))
    torch.testing.assert_close(planes[:, :4], with_prior(torch.zeros(4, 3, 64, 64), torch.zeros(4)))


def test_a_distance_tracker_reads_both_priors_and_hands_both_on(pod: Path, tmp_path: Path) -> None:
    """Started from a tracker of the azimuth alone, the distance plane comes in through zero weights; trained, the
    engines read the distance and give (azimuth, distance) as the next prior, what the latent decodes to."""
    tracker = tmp_path / "tracker.pt"
    started, _, frames = started_from_general(pod, track=True)
    torch.save(make_checkpoint(started, 8.0, 1, 0.0, {}), tracker)
    run(_settings(pod, tmp_path / "run", epochs=1, lr=1e-3, batch_size=16, init=str(tracker), prior_distance=True))
    checkpoint = tmp_path / "run" / "last.pt"
    assert torch.load(checkpoint, weights_only=True)["config"]["prior_distance"] is True
    fresh = CMVAE(input_norm="channel", track=True, prior_distance=True)
    load_init_weights(fresh, str(tracker), n_z=10)
    azimuths = torch.linspace(-20, 20, 8)
    with torch.no_grad():
        near = fresh.eval().encode(with_prior(frames, torch.stack([azimuths, torch.full((8,), 3.0)], dim=1)))
        torch.testing.assert_close(near, started.encode(with_prior(frames, azimuths)), rtol=1e-5, atol=1e-5)

    images = np.load(pod / "shard-00001.images.npy")[:6]
    priors = np.array([[-15.0, 4.0], [-5.0, 5.0], [0.0, 0.0], [3.0, 6.0], [10.0, 7.0], [20.0, 8.0]], np.float32)
    encoder = LatentEncoder(checkpoint)
    assert encoder.prior_shape == (2,)
    mu, _, next_priors = encoder.track(images, priors)
    farther = priors + np.array([0.0, 2.0], np.float32)
    assert np.abs(encoder.encode(images, farther)[0] - mu).max() > 1e-4  # the distance is read
    state = encoder.decode_state(mu)
    np.testing.assert_allclose(next_priors, np.stack([state[1], state[0]], axis=1), rtol=1e-5, atol=1e-4)
    onnx_mu, _, onnx_next = LatentEncoder(checkpoint, engine="onnx").track(images, priors)
    np.testing.assert_allclose(onnx_mu, mu, rtol=1e-4, atol=3e-4)
    np.testing.assert_allclose(onnx_next, next_priors, atol=1e-2)
    with pytest.raises(ValueError, match=r"priors must be 6 finite azimuths in degrees and distances in metres"):
        encoder.encode(images, priors[:, 0])
    from encoder_service.service import EncoderSettings, check

    for served in (checkpoint, tracker):  # the wire's prior is a list of numbers: both serve (protocol 6)
        check(EncoderSettings(checkpoint=str(served)))
    with pytest.raises(ValueError, match="--prior-distance is a tracking encoder's prior: give --track too"):
        run(_settings(pod, tmp_path / "untracked", track=False, prior_distance=True))
