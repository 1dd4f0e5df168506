"""`swimm eval --suite` on the in-process backend: every condition played once per contender, the encoder's reading
of each condition, and a run folder that says how it was made. Real MuJoCo rendering and the shipped CMVAE."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import matplotlib.image
import pandas as pd
import pytest

from eval_service import command
from eval_service.command import EvalCommandSettings
from eval_service.suite import REFERENCES, SuiteSettings, run_suite
from services.results import file_sha256
from sim_service.splits import SPLITS

SPLIT_NAMES = ["tannin", "dark", "shoals"]


def settings(tmp_path: Path, **overrides) -> EvalCommandSettings:
    base = EvalCommandSettings(backend="inprocess", obs="state", algo=["scripted"], episodes=2, steps=30, seed=131,
                               progress_bar=False, figures=True, out=str(tmp_path / "suite"), suite=True,
                               suite_plan=SuiteSettings(splits=SPLIT_NAMES, frames=6))  # fmt: skip
    return replace(base, **overrides)


def test_a_suite_plays_every_condition_and_reads_each_with_the_encoder(tmp_path) -> None:
    given = settings(tmp_path)
    out = Path(given.out)
    table = run_suite(given, given.suite_plan, out)
    conditions = [split.name for split in REFERENCES] + SPLIT_NAMES
    assert list(table["condition"]) == conditions and set(table["label"]) == {"scripted"}
    episodes = pd.read_csv(out / "episodes.csv")
    assert len(episodes) == len(conditions) * given.episodes
    for condition, part in episodes.groupby("condition"):  # the table's returns are its episodes' mean
        assert table.set_index("condition").loc[condition, "mean_return"] == pytest.approx(part["return"].mean())
    # the same seeds in every condition: the ground-truth tracker never reads frames, so its returns match exactly
    assert episodes.groupby("condition")["return"].apply(tuple).nunique() == 1

    encoder = pd.read_csv(out / "encoder.csv")
    assert list(encoder["condition"]) == conditions and (encoder["frames"] == 6).all()
    errors = encoder.set_index("condition")
    assert errors.loc["clean", "d_mae_m"] < 1.0 and errors.loc["clean", "theta_mae_deg"] < 3.0
    assert errors.loc["dark", "d_mae_m"] > errors.loc["clean", "d_mae_m"]  # dark water fools the clean CMVAE

    record = json.loads((out / "suite.json").read_text())
    about = record["provenance"]
    assert len(about["git"]["commit"]) == 40 and about["host"]["cores"] >= 1
    cmvae = about["models"]["cmvae"]
    assert cmvae["sha256"] == file_sha256(cmvae["path"])
    assert len(about["episode_seeds"]) == given.episodes and about["seeds"] == [131]
    assert [c["name"] for c in record["conditions"]] == conditions
    assert record["conditions"][2]["noise"]["fog_color"] == SPLITS["tannin"].noise.fog_color
    assert (
        record["conditions"][4]["scene"]["fish_shoals"] == [3, 3]
        and record["conditions"][2]["scene"]["preset"] == "plain"
    )
    assert matplotlib.image.imread(out / "suite.png").shape[0] > 100


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"suite_plan": SuiteSettings(splits=["lagoon"])}, "unknown split lagoon"),
        ({"suite_plan": SuiteSettings(splits=SPLIT_NAMES, frames=-1)}, "--suite-frames must be >= 0"),
        ({"sweep": True}, "--suite is a run of its own"),
    ],
)
def test_bad_suite_settings_are_refused_by_name(tmp_path, overrides, message) -> None:
    with pytest.raises(ValueError, match=message):
        command.check(settings(tmp_path, **overrides))
    assert not Path(settings(tmp_path).out).exists()


def test_a_suite_reads_frames_with_a_pod_detector_too(tmp_path) -> None:
    given = settings(tmp_path, episodes=1, steps=5, encoder_checkpoint="encoder_service/models/pod_detector.pt",
                     suite_plan=SuiteSettings(splits=["dark"], frames=6))  # fmt: skip
    run_suite(given, given.suite_plan, Path(given.out))
    errors = pd.read_csv(Path(given.out) / "encoder.csv").set_index("condition")
    assert list(errors.index) == ["clean", "murky", "dark"]
    assert errors.loc["clean", "theta_mae_deg"] < 3.0  # a lone dolphin in clean water, read by its centre's peak
