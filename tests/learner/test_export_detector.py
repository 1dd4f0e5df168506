"""`swimm export` of a policy on the pod detector, and `swimm pilot` flying the pair: the detector's file and the
actor's agree with the Python path on real frames through the same tracker, the actor reads the tracker's reading as
the detector's encoder places it in the latent, the pilot joins the pair without torch, and a pair that does not
belong together is refused by name."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime
import pytest

from encoder_service.model import normalise_labels
from learner_service.export import ExportSettings, run
from learner_service.export_detector import detector_file
from pilot_service.policy import ContractError, OnnxPolicy
from services.pod_tracker import UNSEEN, TargetReader
from tests.learner.untrained import untrained_sac

DETECTOR = Path("encoder_service/models/pod_detector.pt")
FRAMES = 120


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> Path:
    """An untrained camera-only SAC on the shipped pod detector, exported and checked (its 20-step episodes: several
    engagements in the check)."""
    root = tmp_path_factory.mktemp("detector-export")
    untrained_sac(DETECTOR, "planar", root / "on-detector.zip")
    out = root / "policy.onnx"
    assert run(ExportSettings(checkpoint=str(root / "on-detector.zip"), out=str(out), check_frames=FRAMES)) == 0
    return out


def test_the_pair_agrees_with_the_python_path_and_names_its_detector(pair: Path) -> None:
    report = json.loads(pair.with_suffix(".json").read_text())
    assert report["frames_checked"] == FRAMES and report["max_action_difference"] <= 1e-2
    assert report["max_reading_difference"] <= 1e-2 and report["onnx_ms_per_frame"] > 0
    detector = detector_file(pair)
    assert detector.name == "policy.detector.onnx" and report["detector_bytes"] == detector.stat().st_size
    assert not list(pair.parent.glob("*.partial"))
    session = onnxruntime.InferenceSession(str(pair), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["reading", "action_history"]
    contract = json.loads(session.get_modelmeta().custom_metadata_map["swimm.contract"])
    perception = contract["perception"]
    assert perception["detector"] == detector.name and perception["kind"] == "pod-detector"
    assert perception["stride"] in (2, 4) and 0 < perception["threshold"] < 1 and "gate" in perception["tracker"]
    assert "frame" not in contract["inputs"] and "reading" in contract["inputs"]
    frames = np.random.default_rng(0).integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    heat, regression = onnxruntime.InferenceSession(str(detector)).run(None, {"frame": frames})
    grid = 64 // perception["stride"]
    assert heat.shape == (2, grid, grid) and regression.shape == (2, 3, grid, grid)
    assert np.all((heat > 0) & (heat < 1))


def test_the_actor_reads_the_reading_as_the_detectors_encoder_places_it(pair: Path) -> None:
    """The actor file on (distance, azimuth) acts as the model does on the latent the in-process encoder builds
    from the same reading (normalised d and theta, psi 0, the rest 0)."""
    from stable_baselines3 import SAC

    model = SAC.load(pair.with_name("on-detector.zip"), device="cpu")
    session = onnxruntime.InferenceSession(str(pair), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    readings = np.stack([rng.uniform(2, 10, 8), rng.uniform(-40, 40, 8)], axis=1).astype(np.float32)
    history = rng.uniform(-1, 1, (8, 20)).astype(np.float32)
    action, _ = session.run(None, {"reading": readings, "action_history": history})
    latent = np.zeros((8, 10), np.float32)
    latent[:, :3] = normalise_labels(np.concatenate([readings, np.zeros((8, 1))], axis=1))
    expected, _ = model.predict(np.concatenate([latent, history], axis=1), deterministic=True)
    np.testing.assert_allclose(action, expected, atol=1e-5)


def test_the_pilot_joins_the_pair_through_the_tracker_and_a_reset_engages_again(pair: Path) -> None:
    """OnnxPolicy acts as the detector file, the tracker and the actor file joined by hand; reset(azimuth)
    engages afresh near that bearing, reset() at the centre."""
    policy = OnnxPolicy(pair)
    assert policy.tracks and policy.image_size == 64 and policy.action_names == ["surge", "yaw"]
    detect = onnxruntime.InferenceSession(str(detector_file(pair)), providers=["CPUExecutionProvider"])
    act = onnxruntime.InferenceSession(str(pair), providers=["CPUExecutionProvider"])
    perception = policy.contract["perception"]
    reader = TargetReader(lambda f: detect.run(None, {"frame": f}), perception["threshold"], perception["stride"], 64)
    from sim_service.settings import WorldSettings
    from sim_service.world import World

    world = World(WorldSettings())
    try:
        frames = [world.reset(seed)[1] for seed in (5, 6, 7)]
    finally:
        world.close()
    history = np.zeros((1, 20), np.float32)
    for frame in frames:
        reading = np.float32([reader.read(frame)])
        assert reading[0, 0] != UNSEEN[0] or reading[0, 1] != UNSEEN[1]  # the reset frames show the dolphin
        action, history = act.run(None, {"reading": reading, "action_history": history})
        np.testing.assert_array_equal(policy.act(frame), action[0])
    policy.reset(-30.0)
    assert policy.reader.engage_deg == -30.0 and policy.reader.state is None
    assert not policy.state["action_history"].any()
    policy.reset()
    assert policy.reader.engage_deg == 0.0


def test_it_flies_where_torch_is_not_installed(pair: Path) -> None:
    script = (
        "import sys; sys.modules['torch'] = None; sys.modules['stable_baselines3'] = None\n"
        "import numpy as np\n"
        "from pilot_service.policy import OnnxPolicy\n"
        f"policy = OnnxPolicy({str(pair)!r})\n"
        "print(policy.act(np.zeros((64, 64, 3), np.uint8)).shape)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "(2,)"


def test_a_pair_that_does_not_belong_together_is_refused_by_name(pair: Path, tmp_path: Path) -> None:
    alone = tmp_path / "renamed.onnx"  # the contract names the detector file by the name it was written with
    shutil.copy(pair, alone)
    with pytest.raises(ContractError, match=r"policy\.detector\.onnx, which does not exist"):
        OnnxPolicy(alone)
    shutil.copy(pair, tmp_path / "policy.onnx")
    (tmp_path / "policy.detector.onnx").write_bytes(detector_file(pair).read_bytes()[:-1] + b"\0")
    with pytest.raises(ContractError, match=r"policy\.detector\.onnx is not the detector .* exported with"):
        OnnxPolicy(tmp_path / "policy.onnx")


def test_a_check_that_fails_leaves_neither_file(pair: Path, tmp_path: Path) -> None:
    out = tmp_path / "strict.onnx"
    settings = ExportSettings(checkpoint=str(pair.with_name("on-detector.zip")), out=str(out), check_frames=20,
                              detector_tolerance=1e-12)  # fmt: skip
    with pytest.raises(ValueError, match="differs from the Python path's .* the files are not kept"):
        run(settings)
    assert not list(tmp_path.iterdir())
