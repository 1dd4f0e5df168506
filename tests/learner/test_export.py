"""`swimm export` end to end on the shipped policy: the ONNX file agrees with the Python path on real frames,
carries its contract, runs without torch or stable-baselines3, and a bad request leaves no file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime
import pytest

from learner_service.envs import make_vec_env
from learner_service.export import ExportSettings, episode_frames, run
from learner_service.identity import policy_identity, stamp
from learner_service.registry import make_model
from learner_service.task import TaskSettings
from services.geometry import HFOV_DEG
from tests.learner.untrained import untrained_sac

FRAMES = 120


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "policy.onnx"
    assert run(ExportSettings(out=str(out), check_frames=FRAMES)) == 0
    return out


def test_the_file_agrees_with_the_python_path_and_reports_it(exported: Path) -> None:
    report = json.loads(exported.with_suffix(".json").read_text())
    assert report["frames_checked"] == FRAMES and report["max_action_difference"] <= 1e-4
    assert report["bytes"] == exported.stat().st_size
    assert report["onnx_ms_per_frame"] > 0 and report["torch_ms_per_frame"] > 0
    assert not exported.with_name(exported.name + ".partial").exists()


def test_the_contract_is_in_the_metadata_and_the_batch_is_free(exported: Path) -> None:
    session = onnxruntime.InferenceSession(str(exported), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    contract = json.loads(meta["swimm.contract"])
    assert contract["action_names"] == ["surge", "yaw"] and contract["control_rate_hz"] == 50
    assert meta["swimm.algo"] == "sac" and len(meta["swimm.policy_sha256"]) == 64
    assert [i.name for i in session.get_inputs()] == ["frame", "action_history"]  # no prior: this CMVAE does not track
    assert [o.name for o in session.get_outputs()] == ["action", "next_history"] and "prior" not in contract["inputs"]
    frames = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    history = np.random.default_rng(1).uniform(-1, 1, (3, 20)).astype(np.float32)
    action, next_history = session.run(None, {"frame": frames, "action_history": history})
    assert action.shape == (3, 2) and np.all(np.abs(action) <= 1.0)
    np.testing.assert_array_equal(next_history[:, :18], history[:, 2:])  # ActPrev shifts by one action...
    np.testing.assert_array_equal(next_history[:, 18:], action)  # ...and ends with the one just chosen


def test_it_runs_where_neither_torch_nor_stable_baselines3_is_installed(exported: Path) -> None:
    script = (
        "import sys; sys.modules['torch'] = None; sys.modules['stable_baselines3'] = None\n"
        "import numpy as np, onnxruntime\n"
        f"session = onnxruntime.InferenceSession({str(exported)!r}, providers=['CPUExecutionProvider'])\n"
        "action, _ = session.run(None, {'frame': np.zeros((1, 64, 64, 3), np.uint8),"
        " 'action_history': np.zeros((1, 20), np.float32)})\n"
        "print(action.shape)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "(1, 2)"


def test_the_recorded_episode_is_the_python_paths_own(exported: Path) -> None:
    """The frames the check replays are those the model acted on: ActPrev ends with the previous action."""
    from stable_baselines3 import SAC

    from learner_service.export import SHIPPED_POLICY
    from learner_service.task import TrackingTask

    model = SAC.load(SHIPPED_POLICY, device="cpu")
    recorded = episode_frames(model, TrackingTask(TaskSettings(obs="cmvae")), Path(
        "encoder_service/models/cmvae.pt"), 30, 9001)  # fmt: skip
    np.testing.assert_allclose(recorded["action_history"][1:, -2:], np.clip(recorded["action"][:-1], -1, 1))
    assert recorded["frame"].shape == (30, 64, 64, 3) and len(np.unique(recorded["frame"][:, 32, 32, 0])) > 1
    assert not recorded["prior"].any()  # a CMVAE that does not track is fed none


def test_bad_requests_name_the_problem_and_leave_no_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="policy checkpoint .*nowhere.zip does not exist"):
        run(ExportSettings(checkpoint=str(tmp_path / "nowhere.zip"), out=str(tmp_path / "a.onnx")))
    for task in ("planar", "3d"):
        env = make_vec_env("inprocess", TaskSettings(obs="state", task=task, max_steps=20), n_envs=1, base_seed=1)
        try:
            model = make_model("sac", env, seed=1, overrides={"device": "cpu", "buffer_size": 100})
            stamp(model, policy_identity("", "state", "swimm2", task))
            model.save(tmp_path / f"state-{task}.zip")
        finally:
            env.close()
    with pytest.raises(ValueError, match="only camera-only \\(cmvae\\) policies export"):
        run(ExportSettings(checkpoint=str(tmp_path / "state-planar.zip"), out=str(tmp_path / "b.onnx")))
    with pytest.raises(ValueError, match="only camera-only \\(cmvae\\) policies export"):
        run(ExportSettings(checkpoint=str(tmp_path / "state-3d.zip"), out=str(tmp_path / "b.onnx")))
    with pytest.raises(ValueError, match="not kept"):
        run(ExportSettings(out=str(tmp_path / "c.onnx"), check_frames=20, tolerance=1e-12))
    assert not list(tmp_path.glob("*.onnx*"))


def test_the_policy_to_fly_exports_with_the_cmvae_it_records(exported: Path) -> None:
    """cmvae_fans.pt (a fine-tune of cmvae_wide.pt) white-balances each frame, takes its added light away and averages
    it with its mirror image, all inside its encoder module, so the ONNX graph does too (the agreement within 1e-4
    above is on real frames): the file carries that CMVAE, the one the policy records."""
    from learner_service.export import SHIPPED_POLICY
    from learner_service.identity import encoder_for
    from services.results import file_sha256

    recorded = encoder_for(SHIPPED_POLICY, None)
    assert recorded.name == "cmvae_fans.pt"
    session = onnxruntime.InferenceSession(str(exported), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["swimm.encoder_sha256"] == file_sha256(recorded)
    assert meta["swimm.policy_sha256"] == file_sha256(SHIPPED_POLICY)


def test_a_3d_policy_exports_its_three_actions_and_the_pilot_flies_them(tmp_path: Path) -> None:
    from encoder_service import DEFAULT_CHECKPOINT
    from pilot_service.policy import OnnxPolicy

    untrained_sac(DEFAULT_CHECKPOINT, "3d", tmp_path / "cmvae-3d.zip")
    out = tmp_path / "3d.onnx"
    assert run(ExportSettings(checkpoint=str(tmp_path / "cmvae-3d.zip"), out=str(out), check_frames=20)) == 0
    assert json.loads(out.with_suffix(".json").read_text())["max_action_difference"] <= 1e-4
    policy = OnnxPolicy(out)
    assert policy.action_names == ["surge", "heave", "yaw"] and policy.contract["task"] == "3d"
    assert policy.history_size == 30 and policy.act(np.zeros((64, 64, 3), np.uint8)).shape == (3,)


def test_a_policy_on_a_mirror_averaging_cmvae_exports_reading_each_frame_twice(tmp_path: Path) -> None:
    """A CMVAE with --mirror-average reads each frame and its mirror image inside its module: the exported graph
    does too, and its actions match the Python path's within 1e-4 on real frames."""
    import torch

    from encoder_service.model import read_checkpoint

    checkpoint = read_checkpoint("encoder_service/models/cmvae_light.pt")
    checkpoint["config"]["mirror_average"] = True
    cmvae = tmp_path / "cmvae_light_mirror.pt"
    torch.save(checkpoint, cmvae)
    untrained_sac(cmvae, "planar", tmp_path / "mirror.zip")
    out = tmp_path / "mirror.onnx"
    assert run(ExportSettings(checkpoint=str(tmp_path / "mirror.zip"), out=str(out), check_frames=20)) == 0
    assert json.loads(out.with_suffix(".json").read_text())["max_action_difference"] <= 1e-4


@pytest.fixture(scope="module")
def tracking_export(tmp_path_factory) -> Path:
    """An untrained camera-only SAC on a tracking CMVAE whose latent reads the prior (its stripe's weights drawn at
    random: the shipped weights start them at zero), exported and checked."""
    import torch

    from encoder_service.model import CMVAE, make_checkpoint
    from encoder_service.train import load_init_weights

    root = tmp_path_factory.mktemp("tracking")
    cmvae = CMVAE(input_norm="channel", track=True)
    load_init_weights(cmvae, "encoder_service/models/cmvae_general.pt", n_z=10)
    with torch.no_grad():
        cmvae.encoder.features[0].weight[:, 3] = torch.randn_like(cmvae.encoder.features[0].weight[:, 3]) * 0.1
    torch.save(make_checkpoint(cmvae.eval(), 8.0, 1, 0.0, {}), root / "tracking.pt")
    untrained_sac(root / "tracking.pt", "planar", root / "cmvae-tracking.zip")
    out = root / "tracking.onnx"
    assert run(ExportSettings(checkpoint=str(root / "cmvae-tracking.zip"), out=str(out), check_frames=FRAMES)) == 0
    return out


def test_a_policy_on_a_tracking_cmvae_carries_its_prior_and_agrees_with_the_python_path(tracking_export: Path) -> None:
    """The file takes the prior and gives the next one, documented in its contract; the export's own check fed it
    the in-process episode's priors and its actions and next priors matched the Python path's; the next prior is the
    azimuth the encoder's latent decodes to, and the action depends on the prior."""
    from encoder_service.inference import LatentEncoder

    report = json.loads(tracking_export.with_suffix(".json").read_text())
    assert report["max_action_difference"] <= 1e-4 and report["max_next_prior_difference"] <= 4e-3
    session = onnxruntime.InferenceSession(str(tracking_export), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["frame", "action_history", "prior"]
    assert [o.name for o in session.get_outputs()] == ["action", "next_history", "next_prior"]
    contract = json.loads(session.get_modelmeta().custom_metadata_map["swimm.contract"])
    assert "prior" in contract["inputs"] and "next_prior" in contract["outputs"]

    frames = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    priors = np.array([-20.0, 0.0, 15.0], np.float32)
    feeds = {"frame": frames, "action_history": np.zeros((3, 20), np.float32), "prior": priors}
    action, _, next_prior = session.run(None, feeds)
    encoder = LatentEncoder(tracking_export.with_name("tracking.pt"))
    np.testing.assert_allclose(next_prior, encoder.track(frames, priors)[2], atol=1e-3)
    assert np.abs(session.run(["action"], feeds | {"prior": -priors})[0] - action).max() > 1e-4  # the prior is read


def test_the_recorded_priors_are_those_the_in_process_env_fed_a_tracking_cmvae(tracking_export: Path) -> None:
    """Each frame's prior is the previous frame's next prior, and the image centre at each 20-step episode's start
    (the frame that ended an episode dropped, as never acted on)."""
    from stable_baselines3 import SAC

    from learner_service.task import TrackingTask

    model = SAC.load(tracking_export.with_name("cmvae-tracking.zip"), device="cpu")
    task = TrackingTask(TaskSettings(obs="cmvae", max_steps=20))
    recorded = episode_frames(model, task, tracking_export.with_name("tracking.pt"), 45, 9001)
    assert recorded["prior"][0] == 0.0 and recorded["prior"][20] == 0.0 and recorded["prior"][40] == 0.0
    np.testing.assert_array_equal(recorded["prior"][1:20], recorded["next_prior"][:19])
    np.testing.assert_array_equal(recorded["prior"][21:40], recorded["next_prior"][20:39])
    assert np.all(recorded["prior"][1:20] != 0.0)


def test_the_pilot_feeds_a_tracking_policy_its_last_next_prior_and_the_centre_after_a_reset(
    tracking_export: Path,
) -> None:
    """`swimm pilot`'s policy runner acts as onnxruntime fed by hand each frame's previous next_prior (and next
    history), and after a reset (frames back after the watchdog) as at an episode's start: the prior at 0."""
    from pilot_service.policy import OnnxPolicy

    policy = OnnxPolicy(tracking_export)
    session = onnxruntime.InferenceSession(str(tracking_export), providers=["CPUExecutionProvider"])
    frames = np.random.default_rng(2).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    history, prior = np.zeros((1, 20), np.float32), np.zeros(1, np.float32)
    for frame in frames:
        action, history, prior = session.run(None, {"frame": frame[None], "action_history": history, "prior": prior})
        np.testing.assert_array_equal(policy.act(frame), action[0])
        assert prior[0] != 0.0  # what the next frame is fed
    policy.reset()
    fresh = {"frame": frames[:1], "action_history": np.zeros((1, 20), np.float32), "prior": np.zeros(1, np.float32)}
    first = session.run(["action"], fresh)[0]
    assert not np.array_equal(session.run(["action"], fresh | {"prior": prior})[0], first)  # the reset prior mattered
    np.testing.assert_array_equal(policy.act(frames[0]), first[0])


def test_a_target_box_starts_a_tracking_policys_prior_at_the_boxes_azimuth(tracking_export: Path, tmp_path) -> None:
    """`swimm pilot --target-box X Y W H`: the first frame is read with the prior at the azimuth of the box's centre
    (its pinhole bearing, + = left), where without a box it starts at the centre."""
    import csv
    import threading

    import cv2

    from pilot_service.frames import FrameSource, as_sim_frame, box_azimuth_deg
    from pilot_service.pilot import PilotSettings, fly, limited
    from pilot_service.policy import OnnxPolicy

    assert box_azimuth_deg((60, 0, 40, 10), 160, 90.0) == pytest.approx(0.0)  # centred
    assert box_azimuth_deg((0, 0, 0, 10), 160, 90.0) == pytest.approx(45.0)  # the left edge of a 90-degree view
    assert box_azimuth_deg((100, 0, 40, 10), 160, 90.0) == pytest.approx(-np.degrees(np.arctan(0.5)))  # 3/4 across

    video = tmp_path / "frames.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (160, 160))
    for frame in np.random.default_rng(3).integers(0, 256, (3, 160, 160, 3), dtype=np.uint8):
        writer.write(frame)
    writer.release()
    box = [30, 40, 20, 30]  # centred a quarter of the width left of the middle
    settings = PilotSettings(policy=str(tracking_export), source=str(video), camera_hfov_deg=HFOV_DEG, dry_run=True,
                             rate_hz=50, target_box=box, out=str(tmp_path / "pilot"))  # fmt: skip
    with fly(settings, threading.Event()).open() as rows:
        first = next(row for row in csv.DictReader(rows) if row["frame"] == "1")

    source = FrameSource(str(video))
    seen = as_sim_frame(source.read(), HFOV_DEG, 64)
    source.close()
    policy = OnnxPolicy(tracking_export)
    policy.reset(box_azimuth_deg(tuple(box), 160, HFOV_DEG))
    assert policy.state["prior"][0] == pytest.approx(np.degrees(np.arctan(0.5 * np.tan(np.radians(HFOV_DEG / 2)))))
    expected = limited(policy.act(seen), policy.action_names, settings)
    assert (float(first["surge"]), float(first["yaw"])) == pytest.approx((expected["surge"], expected["yaw"]), abs=1e-6)
    policy.reset()
    centred = limited(policy.act(seen), policy.action_names, settings)
    assert (centred["surge"], centred["yaw"]) != pytest.approx((expected["surge"], expected["yaw"]), abs=1e-6)


def test_a_target_box_the_policy_cannot_use_is_refused_by_name(tracking_export: Path, tmp_path) -> None:
    import threading

    from pilot_service.pilot import PilotSettings, fly, target_azimuth_deg

    with pytest.raises(ValueError, match="--target-box takes X Y W H"):
        PilotSettings(target_box=[1, 2, 3]).check()
    frame = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(ValueError, match="reaches past the 160 x 120 frame"):
        target_azimuth_deg(PilotSettings(target_box=[150, 0, 20, 20]), frame)
    with pytest.raises(ValueError, match="outside the"):  # a wide lens's edge: outside the view the policy is shown
        target_azimuth_deg(PilotSettings(target_box=[0, 0, 4, 4], camera_hfov_deg=110.0), frame)
    plain = tmp_path / "plain.onnx"
    assert run(ExportSettings(out=str(plain), check_frames=5)) == 0
    with pytest.raises(ValueError, match="reads no prior"):
        fly(PilotSettings(policy=str(plain), source="missing.mp4", dry_run=True, target_box=[0, 0, 8, 8]),
            threading.Event())  # fmt: skip
