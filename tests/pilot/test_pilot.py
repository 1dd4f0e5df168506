"""`swimm pilot` on real libraries: the exported policy under onnxruntime, a sim-rendered dive video read with
OpenCV's FFmpeg (from a file, and as an H.264 RTP stream that ffmpeg sends over loopback), and MANUAL_CONTROL to a
pymavlink stand-in for ArduSub in a process of its own."""

from __future__ import annotations

import base64
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from pilot_service.frames import FrameSource, SourceError, as_sim_frame, crop_box
from pilot_service.pilot import PilotSettings, check_dive_mode, fly, limited
from pilot_service.policy import ContractError, OnnxPolicy
from pilot_service.vehicle import Vehicle, VehicleError
from services.geometry import HFOV_DEG

FRAMES = 30
FPS = 10


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    from learner_service.export import ExportSettings, run

    out = tmp_path_factory.mktemp("export") / "policy.onnx"
    assert run(ExportSettings(out=str(out), check_frames=30)) == 0
    return out


@pytest.fixture(scope="module")
def dive_video(tmp_path_factory) -> Path:
    """A sim episode filmed at 160 x 160, 10 frames a second: the 'real' camera (square, the sim's horizontal field)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from sim_service.settings import WorldSettings
    from sim_service.world import World

    path = tmp_path_factory.mktemp("video") / "dive.mp4"
    world = World(WorldSettings(image_size=160))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (160, 160))
    try:
        _, frame = world.reset(2024)
        for step in range(FRAMES):
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            for _ in range(5):  # 50 Hz physics, 10 Hz film
                _, frame = world.step((0.0, 0.0, 0.3, 0.2 * np.sin(step / 3)))
    finally:
        writer.release()
        world.close()
    return path


def controls(path: Path) -> list[dict[str, str]]:
    with path.open() as handle:
        return list(csv.DictReader(handle))


def test_the_crop_keeps_the_sim_cameras_view() -> None:
    assert crop_box(160, 160, HFOV_DEG)[::2] == (0, 160)  # the same horizontal field: all of the width
    x, y, w, h = crop_box(1920, 1080, 110.0)  # a wider lens: the middle of the frame
    assert 0 < x and 0 < y and w < 1920 and h < 1080 and (x, y) == ((1920 - w) // 2, (1080 - h) // 2)


def test_a_dry_run_on_a_dive_video_acts_as_the_policy_on_each_frame(exported: Path, dive_video: Path, tmp_path) -> None:
    settings = PilotSettings(policy=str(exported), source=str(dive_video), camera_hfov_deg=HFOV_DEG, dry_run=True,
                             rate_hz=50, out=str(tmp_path / "pilot"))  # fmt: skip
    rows = controls(fly(settings, threading.Event()))
    first_of_frame = {}
    for row in rows:
        first_of_frame.setdefault(int(row["frame"]), row)
    first_of_frame.pop(0, None)  # neutral ticks before the first frame came
    assert sorted(first_of_frame) == list(range(1, FRAMES + 1))  # every frame of the file used, none skipped

    policy, source, expected, seen = OnnxPolicy(exported), FrameSource(str(dive_video)), [], []
    while (frame := source.read()) is not None:
        seen.append(as_sim_frame(frame, HFOV_DEG, 64))
        command = limited(policy.act(seen[-1]), policy.action_names, settings)
        expected.append((command["surge"], command["heave"], command["yaw"]))
    source.close()
    got = [(float(row["surge"]), float(row["heave"]), float(row["yaw"])) for _, row in sorted(first_of_frame.items())]
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert all(heave == 0.0 for _, heave, _ in got)  # a planar policy holds depth
    assert max(abs(surge) for surge, _, _ in got) <= settings.max_surge and all(row["sent"] == "" for row in rows)

    # The session as a viewer reads it: each frame the policy saw, bit for bit, and every control row.
    recorded = _session(tmp_path / "pilot" / "session.mcap")
    frames = [cv2.cvtColor(cv2.imdecode(np.frombuffer(base64.b64decode(body["data"]), np.uint8), cv2.IMREAD_COLOR),
                           cv2.COLOR_BGR2RGB) for body in recorded["pilot/camera"]]  # fmt: skip
    assert len(frames) == FRAMES and all(np.array_equal(a, b) for a, b in zip(frames, seen, strict=True))
    assert [{key: str(value) for key, value in body.items()} for body in recorded["pilot/controls"]] == rows


@pytest.mark.slow
def test_published_frames_reach_a_live_encoder_as_a_sims_observations(
    exported: Path, dive_video: Path, processes, zenoh_router, zenoh_settings, zenoh_session, tmp_path
) -> None:
    """`--publish`: each frame the policy saw goes out as eval/pilot's observation, and the shipped CMVAE in an
    encoder process answers with the latent it gives that frame in-process."""
    from encoder_service.inference import LatentEncoder
    from services.keys import Keys
    from services.messages import LatentMsg, ObservationMsg, batch_messages
    from services.presence import Roster

    keys = Keys(zenoh_settings(zenoh_router).namespace)
    processes.start("encoder", "encoder", "--connect", zenoh_router, "--namespace", keys.namespace,
                    "--ident", "enc-0", "--threads", "1")  # fmt: skip
    session = zenoh_session(zenoh_router)
    Roster(session, keys, "encoder").wait_for(1, timeout_s=90)
    observations, latents = [], []
    _subscribers = [session.declare_subscriber(keys.obs("eval", "pilot", "*"),
                                               lambda sample: observations.append(sample.payload.to_bytes())),
                    session.declare_subscriber(keys.latent("eval", "pilot"),
                                               lambda sample: latents.append(sample.payload.to_bytes()))]  # fmt: skip
    time.sleep(1.0)  # the subscriptions reach the router
    settings = PilotSettings(policy=str(exported), source=str(dive_video), camera_hfov_deg=HFOV_DEG, dry_run=True,
                             publish=True, zenoh=zenoh_settings(zenoh_router), out=str(tmp_path / "pilot"))  # fmt: skip
    fly(settings, threading.Event())
    time.sleep(2.0)  # the last latents come back

    source, seen = FrameSource(str(dive_video)), []
    while (frame := source.read()) is not None:
        seen.append(as_sim_frame(frame, HFOV_DEG, 64))
    source.close()
    published = [msg for payload in observations for _, msg in batch_messages(payload, ObservationMsg.from_item)]
    assert [msg.seq for msg in published] == list(range(1, FRAMES + 1))
    assert all(np.array_equal(msg.image, frame) for msg, frame in zip(published, seen, strict=True))
    assert all(np.isnan(msg.telemetry.rover_pos[0]) for msg in published)  # a real camera has no ground truth
    answered = {msg.seq: msg for payload in latents for _, msg in batch_messages(payload, LatentMsg.from_item)}
    assert len(answered) >= FRAMES - 5  # the first frames may leave before the pilot has seen the encoder
    encoder = LatentEncoder()
    for seq, msg in answered.items():
        mu, _ = encoder.encode(seen[seq - 1][None])
        np.testing.assert_allclose(np.asarray(msg.mu, np.float32), mu[0], atol=1e-4)


def _session(path: Path) -> dict[str, list[dict]]:
    """The JSON messages of a pilot's session.mcap by topic, read with the mcap library (schemas checked)."""
    from mcap.reader import make_reader

    topics: dict[str, list[dict]] = {}
    with path.open("rb") as handle:
        for schema, channel, message in make_reader(handle).iter_messages(log_time_order=True):
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            assert schema.name == {"pilot/camera": "foxglove.CompressedImage"}.get(channel.topic, "swimm.PilotControl")
            topics.setdefault(channel.topic, []).append(json.loads(message.data))
    return topics


def test_what_cannot_be_flown_is_refused_by_name(exported: Path, tmp_path) -> None:
    with pytest.raises(SourceError, match="no video file at .*missing.mp4"):
        FrameSource(str(tmp_path / "missing.mp4"))
    corrupt = tmp_path / "corrupt.mp4"
    corrupt.write_bytes(b"\x00" * 4096)
    with pytest.raises(SourceError, match="cannot open the video source .*corrupt.mp4"):
        FrameSource(str(corrupt))
    with pytest.raises(ContractError, match="not an ONNX model"):
        OnnxPolicy(corrupt)
    other = tmp_path / "other.onnx"
    _write_foreign_onnx(other)
    with pytest.raises(ContractError, match="is not a swimm policy: inputs \\['x'\\]"):
        OnnxPolicy(other)
    with pytest.raises(ContractError, match="uint8 frames of shape \\(64, 64, 3\\)"):
        OnnxPolicy(exported).act(np.zeros((32, 32, 3), np.uint8))
    started, port = time.monotonic(), _free_udp_port()
    with pytest.raises(VehicleError, match=f"no HEARTBEAT from a vehicle on udpin:127.0.0.1:{port}"):
        Vehicle(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=1.0)
    assert time.monotonic() - started < 5
    with pytest.raises(ValueError, match="--max-surge"):
        PilotSettings(max_surge=1.5).check()
    with pytest.raises(ValueError, match="--max-heave.*got 0.5, 0.5, 0.0"):
        PilotSettings(max_heave=0.0).check()
    with pytest.raises(ValueError, match="--first-frame-timeout-s must be >= 0"):
        PilotSettings(first_frame_timeout_s=-1.0).check()
    for names, problem in ((["surge", "sway"], "drives \\['surge', 'sway'\\]; the pilot flies"),
                           (["surge", "heave", "yaw"], "outputs 2 actions but its contract names")):  # fmt: skip
        relabelled = tmp_path / f"{len(names)}-actions.onnx"
        _with_action_names(exported, names, relabelled)
        with pytest.raises(ContractError, match=problem):
            OnnxPolicy(relabelled)


def test_a_policy_that_drives_heave_climbs_and_dives_in_alt_hold_only() -> None:
    settings = PilotSettings(max_surge=0.5, max_yaw=0.5, max_heave=0.4)
    three = limited(np.array([0.2, -0.9, 0.7], np.float32), ["surge", "heave", "yaw"], settings)
    assert three == pytest.approx({"surge": 0.2, "heave": -0.4, "yaw": 0.5})
    assert limited(np.array([0.2, 0.3], np.float32), ["surge", "yaw"], settings)["heave"] == 0.0
    check_dive_mode(["surge", "heave", "yaw"], "ALT_HOLD")
    check_dive_mode(["surge", "yaw"], "STABILIZE")
    with pytest.raises(ValueError, match="climb rate.*not STABILIZE"):
        check_dive_mode(["surge", "heave", "yaw"], "STABILIZE")


def test_the_vehicle_gets_heave_as_manual_controls_z_about_its_neutral(tmp_path) -> None:
    port, log = _free_udp_port(), tmp_path / "vehicle.jsonl"
    fake = subprocess.Popen([sys.executable, str(Path(__file__).with_name("fake_vehicle.py")),
                             f"udpout:127.0.0.1:{port}", str(log)])  # fmt: skip
    try:
        vehicle = Vehicle(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=10.0)
        sent = [vehicle.send_control(0.5, -0.25, heave=heave) for heave in (0.4, -1.0, 0.0)]
        vehicle.send_control(0.1, 0.1)  # a planar policy's: depth held
        deadline = time.monotonic() + 10
        while sum('"MANUAL_CONTROL"' in line for line in log.read_text().splitlines()) < 4:
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        vehicle.close()
    finally:
        fake.kill()
        fake.wait()
    manual = [json.loads(line) for line in log.read_text().splitlines() if '"MANUAL_CONTROL"' in line]
    assert [(m["x"], m["z"], m["r"]) for m in manual] == [(500, 700, -250), (500, 0, -250), (500, 500, -250),
                                                          (100, 500, 100)]  # fmt: skip
    assert [z for _, _, z, _ in sent] == [700, 0, 500]


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="needs the ffmpeg command to send the RTP stream")
def test_the_pilot_flies_a_vehicle_from_an_rtp_stream_and_goes_neutral_when_it_stops(
    exported: Path, dive_video: Path, spawn, tmp_path
) -> None:
    rtp_port, mavlink_port, rate, timeout_s = _free_udp_port(even=True), _free_udp_port(), 20, 0.5
    vehicle_log = tmp_path / "vehicle.jsonl"
    fake = subprocess.Popen([sys.executable, str(Path(__file__).with_name("fake_vehicle.py")),
                             f"udpout:127.0.0.1:{mavlink_port}", str(vehicle_log)])  # fmt: skip
    out = tmp_path / "pilot"
    pilot = spawn("pilot", "--policy", str(exported), "--source", f"rtp://127.0.0.1:{rtp_port}", "--mavlink",
                  f"udpin:127.0.0.1:{mavlink_port}", "--rate-hz", str(rate), "--frame-timeout-s", str(timeout_s),
                  "--duration-s", "40", "--stream-timeout-s", "3", "--camera-hfov-deg", str(HFOV_DEG),
                  "--out", str(out))  # fmt: skip
    sender = None
    try:
        # The stream starts after the pilot has opened it and waited once in vain: it opens it again.
        deadline = time.monotonic() + 60
        while not pilot.log_path.is_file() or "no frame from" not in pilot.log_path.read_text():
            assert pilot.alive and time.monotonic() < deadline, pilot.log_tail()
            time.sleep(0.2)
        sender = subprocess.Popen(["ffmpeg", "-loglevel", "error", "-re", "-stream_loop", "-1", "-i",
                                   str(dive_video), "-an", "-c:v", "libx264", "-preset", "ultrafast", "-tune",
                                   "zerolatency", "-g", "5", "-x264-params", "repeat-headers=1", "-f", "rtp",
                                   f"rtp://127.0.0.1:{rtp_port}"], stdout=subprocess.DEVNULL)  # fmt: skip
        deadline = time.monotonic() + 40
        while not (out / "controls.csv").is_file() or _frames_used(out / "controls.csv") < 60:  # 6 s of 10 fps
            assert pilot.alive and time.monotonic() < deadline, pilot.log_tail()
            time.sleep(0.2)
        sender.send_signal(signal.SIGKILL)  # the stream is cut
        assert pilot.process.wait(timeout=60) == 1  # the stream stopped: an error, said so, after neutral

    finally:
        for process in (sender, fake):
            if process is not None:
                process.kill()
                process.wait()
    log = pilot.log_path.read_text()
    assert "no frame for" in log and "neutral controls until frames return" in log, log
    assert f"the stream 'rtp://127.0.0.1:{rtp_port}' stopped giving frames" in log, log

    messages = [json.loads(line) for line in vehicle_log.read_text().splitlines()]
    from_us = [m for m in messages if m["src"] == 255]
    assert sum(m["msg"] == "HEARTBEAT" for m in from_us) >= 5  # the ground station's, every second
    assert any(m["msg"] == "SET_MODE" and m["custom_mode"] == 2 for m in from_us)  # ALT_HOLD
    assert not any(m["msg"] == "COMMAND_LONG" for m in from_us)  # never armed without --arm
    manual = [m for m in from_us if m["msg"] == "MANUAL_CONTROL"]
    span = manual[-2]["t"] - manual[0]["t"]
    assert abs((len(manual) - 2) / span - rate) < 0.15 * rate  # sent at the set rate
    sent = [row["sent"] for row in controls(out / "controls.csv")]
    assert [f"{m['x']} {m['y']} {m['z']} {m['r']}" for m in manual[: len(sent)]] == sent  # the policy's values
    assert any(m["x"] != 0 for m in manual)  # it did fly
    # The watchdog: from the last frame's arrival on, neutral within the timeout (and one control tick).
    rows = controls(out / "controls.csv")
    last_frame = min(float(row["time_s"]) for row in rows if int(row["frame"]) == int(rows[-1]["frame"]))
    late = [row for row in rows if float(row["time_s"]) > last_frame + timeout_s + 1.0 / rate]
    assert late and all(row["neutral"] == "True" and row["sent"] == "0 0 500 0" for row in late)
    assert (manual[-1]["x"], manual[-1]["z"], manual[-1]["r"]) == (0, 500, 0)  # left in neutral


def _frames_used(path: Path) -> int:
    rows = controls(path)
    return int(rows[-1]["frame"]) if rows else 0


def _free_udp_port(even: bool = False) -> int:
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        if not even or port % 2 == 0:
            return port


def _with_action_names(exported: Path, names: list[str], path: Path) -> None:
    """A copy of ``exported`` whose contract names other actions than its graph outputs."""
    import onnx

    model = onnx.load(str(exported))
    for prop in model.metadata_props:
        if prop.key == "swimm.contract":
            prop.value = json.dumps(json.loads(prop.value) | {"action_names": names})
    onnx.save(model, str(path))


def _write_foreign_onnx(path: Path) -> None:
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "other",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])  # fmt: skip
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
