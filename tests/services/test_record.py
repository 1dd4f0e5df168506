"""`swimm replay` refuses what it cannot replay, naming the file and the problem, before it connects anywhere."""

from __future__ import annotations

import threading

import pytest

from services.record import RecordSettings, ReplaySettings, replay
from services.settings import ZenohSettings


def test_a_missing_or_foreign_file_is_refused_by_name(tmp_path) -> None:
    settings = ReplaySettings(zenoh=ZenohSettings(startup_timeout_s=0.1), file=str(tmp_path / "none.mcap"))
    with pytest.raises(FileNotFoundError, match="no recording at .*none.mcap"):
        replay(settings, threading.Event())
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file")
    settings.file = str(garbage)
    with pytest.raises(ValueError, match="garbage.mcap is not a readable MCAP recording: .*invalid magic"):
        replay(settings, threading.Event())
    with pytest.raises(ValueError, match="give the recording"):
        replay(ReplaySettings(), threading.Event())


def test_a_negative_duration_is_refused() -> None:
    with pytest.raises(ValueError, match="--duration-s must be >= 0"):
        RecordSettings(duration_s=-1).check()


def test_eval_refuses_a_recording_it_cannot_score_before_connecting(tmp_path) -> None:
    from eval_service.command import EvalCommandSettings, check

    with pytest.raises(FileNotFoundError, match="--recording .*none.mcap: no such file"):
        check(EvalCommandSettings(recording=str(tmp_path / "none.mcap")))
    with pytest.raises(ValueError, match="--recording scores a file offline"):
        check(EvalCommandSettings(recording=str(tmp_path / "none.mcap"), sweep=True))
