"""Evaluation and training figures: valid PNGs, and figures that hold exactly the data they were given."""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib.image
import numpy as np
import pandas as pd
import pytest
from matplotlib.quiver import Quiver

from eval_service import plots
from learner_service import plots as training_plots
from services.geometry import BETA_DEG

PAPER_SAC = {
    "A": 2.67e-2,
    "D": 2.35e-1,
    "A'": 0.0,
    "D'": 0.0,
    "C'": 0.0,
    "S_D": 8.08e-2,
    "S_A": 1.86e-1,
    "mean_return": 2.40e3,
}


def _episodes() -> pd.DataFrame:
    """Two labels, 6 episodes each: 2 distance, 1 visibility and 1 collision violation in all."""
    rows = []
    for label, offset in (("sac", 2000.0), ("td3", 1500.0)):
        for episode in range(6):
            rows.append(
                {
                    "label": label,
                    "episode": episode,
                    "return": offset - 100.0 * episode,
                    "A": 0.05,
                    "D": 0.2,
                    "left_view": label == "td3" and episode == 4,
                    "distance_exceeded": episode == 5,
                    "collided": label == "sac" and episode == 1,
                    "S_D": 0.1,
                    "S_A": 0.2,
                    "first_cause": "",
                }
            )
    return pd.DataFrame(rows)


def _steps(count: int = 250) -> pd.DataFrame:
    """One episode on a circle of radius 8 m, plus rows of another episode that must be ignored."""
    angle = np.arange(count) * 0.01
    episode = pd.DataFrame(
        {
            "label": "sac",
            "episode": 2,
            "step": np.arange(count),
            "rover_x": 8 * np.cos(angle),
            "rover_y": 8 * np.sin(angle),
            "rover_yaw": np.degrees(angle) + 90.0,
            "target_x": 8 * np.cos(angle + 0.75),
            "target_y": 8 * np.sin(angle + 0.75),
            "target_yaw": 0.0,
            "in_frustum": np.arange(count) % 50 != 0,
            "distance_exceeded": False,
            "collided": False,
        }
    )
    other = episode.assign(episode=3, rover_x=100.0)
    return pd.concat([other, episode.iloc[::-1]], ignore_index=True)  # reversed: the plot must sort by step


def _assert_png(path: Path, width: int, height: int) -> None:
    assert path.is_file()
    pixels = matplotlib.image.imread(path)
    assert pixels.shape[:2] == (height, width)
    assert pixels.std() > 0.05  # something was drawn


def test_plot_returns_writes_png(tmp_path):
    path = plots.plot_returns(_episodes(), tmp_path / "nested" / "returns.png")
    assert path == tmp_path / "nested" / "returns.png"
    _assert_png(path, 900, 450)


def test_returns_figure_has_a_line_per_label_and_markers_per_violation():
    ax = plots.returns_figure(_episodes()).axes[0]
    lines = ax.get_lines()
    assert [line.get_label() for line in lines] == ["sac", "td3"]
    np.testing.assert_allclose(lines[0].get_ydata(), [2000, 1900, 1800, 1700, 1600, 1500])
    markers = {collection.get_label(): collection.get_offsets() for collection in ax.collections}
    assert set(markers) == {"distance violated (2)", "visibility violated (1)", "collision violated (1)"}
    np.testing.assert_allclose(markers["visibility violated (1)"], [[4, 1100]])
    np.testing.assert_allclose(markers["collision violated (1)"], [[1, 1900]])
    assert ax.get_xlabel() == "episode" and "return" in ax.get_ylabel()


def test_returns_figure_reads_flags_back_from_csv(tmp_path):
    csv = tmp_path / "episodes.csv"
    _episodes().to_csv(csv, index=False)
    as_text = pd.read_csv(csv, dtype={"left_view": str, "distance_exceeded": str, "collided": str})
    ax = plots.returns_figure(as_text).axes[0]
    assert sorted(len(c.get_offsets()) for c in ax.collections) == [1, 1, 2]


def test_returns_without_violations_has_no_markers():
    clean = _episodes().assign(left_view=False, distance_exceeded=0, collided=False)
    assert len(plots.returns_figure(clean).axes[0].collections) == 0


def test_returns_missing_columns_raise():
    with pytest.raises(ValueError, match="collided"):
        plots.returns_figure(_episodes().drop(columns="collided"))


def test_plot_metrics_writes_png_with_reference(tmp_path):
    summary = {"sac": dict(PAPER_SAC, A=0.03), "td3": dict(PAPER_SAC, S_A=0.45)}
    path = plots.plot_metrics(summary, tmp_path / "metrics.png", PAPER_SAC, "paper SAC")
    _assert_png(path, 1280, 720)


def test_metrics_figure_has_a_panel_per_metric_and_a_bar_per_label_and_reference():
    summary = {"sac": {"A": 0.03, "D": 0.2, "mean_return": 2500.0}, "ppo": {"A": 0.9, "D": 0.8}}
    fig = plots.metrics_figure(summary, {"A": 2.67e-2, "D": 2.35e-1, "mean_return": 2.40e3}, "paper SAC")
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in panels] == ["A", "D", "mean_return"]
    heights = [[patch.get_height() for patch in ax.patches] for ax in panels]
    np.testing.assert_allclose(heights[0], [0.03, 0.9, 2.67e-2])
    np.testing.assert_allclose(heights[2], [2500.0, 2.40e3])  # ppo has no return: its bar is left out
    assert [tick.get_text() for tick in panels[2].get_xticklabels()] == ["sac", "paper SAC"]
    assert panels[0].patches[-1].get_hatch() == "//"


def test_metrics_figure_without_reference_or_metrics():
    fig = plots.metrics_figure({"sac": PAPER_SAC})
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert len(panels) == 8 and all(len(ax.patches) == 1 for ax in panels)
    assert panels[4].get_ylim() == (0.0, 1.0)  # C' is 0: the all-zero panel still has a scale
    with pytest.raises(ValueError):
        plots.metrics_figure({"sac": {"unknown": 1.0}})
    with pytest.raises(ValueError):
        plots.metrics_figure({})


def test_plot_trajectory_writes_png(tmp_path):
    path = plots.plot_trajectory(_steps(), "sac", 2, tmp_path / "trajectory.png", arrow_every=40)
    _assert_png(path, 700, 700)


def test_trajectory_figure_draws_both_paths_ends_and_heading_arrows():
    count, every = 250, 40
    ax = plots.trajectory_figure(_steps(count), "sac", 2, arrow_every=every).axes[0]
    rover, dolphin = ax.get_lines()
    assert (rover.get_label(), dolphin.get_label()) == ("rover", "dolphin")
    assert len(rover.get_xdata()) == count
    np.testing.assert_allclose(rover.get_xdata()[:3], 8 * np.cos([0.0, 0.01, 0.02]))  # sorted by step
    markers = {c.get_label(): c for c in ax.collections if not isinstance(c, Quiver)}
    np.testing.assert_allclose(markers["start"].get_offsets(), [[8.0, 0.0], [8 * np.cos(0.75), 8 * np.sin(0.75)]])
    end_angle = (count - 1) * 0.01
    np.testing.assert_allclose(markers["end"].get_offsets()[0], [8 * np.cos(end_angle), 8 * np.sin(end_angle)])
    assert len(markers["visibility violated (5 steps)"].get_offsets()) == 5  # steps 0, 50, ..., 200
    (arrows,) = [c for c in ax.collections if isinstance(c, Quiver)]
    assert arrows.N == math.ceil(count / every)
    np.testing.assert_allclose(arrows.U[1], math.cos(every * 0.01 + math.pi / 2), atol=1e-9)  # tangent heading
    np.testing.assert_allclose(arrows.V[1], math.sin(every * 0.01 + math.pi / 2), atol=1e-9)
    assert ax.get_aspect() == 1.0
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"


def test_depth_figure_draws_both_depths_and_the_elevation_against_beta(tmp_path):
    count = 250
    steps = _steps(count).assign(rover_z=-4.0, target_z=lambda df: -4.0 + np.sin(df["step"] * 0.02),
                                 elevation=lambda df: 40.0 * np.sin(df["step"] * 0.02))  # fmt: skip
    depth, elevation = plots.depth_figure(steps, "sac", 2).axes
    rover, dolphin = depth.get_lines()
    assert (rover.get_label(), dolphin.get_label()) == ("rover", "dolphin") and len(dolphin.get_xdata()) == count
    np.testing.assert_allclose(dolphin.get_ydata()[:3], -4.0 + np.sin([0.0, 0.02, 0.04]))  # sorted by step
    (band,) = elevation.patches
    np.testing.assert_allclose(band.get_extents().transformed(elevation.transData.inverted()).get_points()[:, 1],
                               [-BETA_DEG, BETA_DEG], atol=1e-6)  # fmt: skip
    assert len(elevation.collections[0].get_offsets()) == 5  # the out-of-view steps 0, 50, ..., 200
    _assert_png(plots.plot_depth(steps, "sac", 2, tmp_path / "depth.png"), 800, 600)
    with pytest.raises(ValueError, match="elevation"):
        plots.depth_figure(_steps(), "sac", 2)


def test_identity_figure_steps_through_the_followed_dolphin_and_shades_the_occluded_steps(tmp_path):
    followed = np.where(np.arange(250) < 100, 0, np.where(np.arange(250) < 120, 2, 0))  # companion 2 at 100-119
    steps = _steps().assign(followed=-1, target_occluded=False)
    steps.loc[steps["episode"] == 2, "followed"] = followed[steps.loc[steps["episode"] == 2, "step"]]
    steps.loc[steps["episode"] == 2, "target_occluded"] = steps["step"].between(100, 119)
    (ax,) = plots.identity_figure(steps, "sac", 2).axes
    (line,) = ax.get_lines()
    np.testing.assert_array_equal(line.get_ydata(), followed)  # sorted by step, the other episode left out
    assert [tick.get_text() for tick in ax.get_yticklabels()] == ["none", "target", "companion 1", "companion 2"]
    assert ax.get_legend_handles_labels()[1] == ["target occluded (20 steps)", "followed"]
    _assert_png(plots.plot_identity(steps, "sac", 2, tmp_path / "identity.png"), 800, 350)
    with pytest.raises(ValueError, match="followed"):
        plots.identity_figure(_steps(), "sac", 2)


def test_trajectory_of_unknown_episode_raises():
    with pytest.raises(ValueError, match="no steps"):
        plots.trajectory_figure(_steps(), "sac", 7)


def _write_monitor(path: Path, t_start: float, rewards: list[float], lengths: list[int], causes: list[str]) -> Path:
    frame = pd.DataFrame(
        {"r": rewards, "l": lengths, "t": np.arange(1, len(rewards) + 1, dtype=float), "cause": causes}
    )
    path.write_text("#" + json.dumps({"t_start": t_start, "env_id": "swimm"}) + "\n" + frame.to_csv(index=False))
    return path


def _monitors(tmp_path: Path) -> list[Path]:
    first = _write_monitor(
        tmp_path / "0.monitor.csv", 1000.0, [10.0, 20.0, 30.0], [100, 200, 300], ["distance", "", "visibility"]
    )
    second = _write_monitor(tmp_path / "1.monitor.csv", 1001.5, [15.0, 25.0], [150, 3000], ["collision", ""])
    return [first, second]


def test_read_monitor_puts_parallel_files_on_one_clock(tmp_path):
    episodes = training_plots.read_monitor(_monitors(tmp_path))
    ordered = episodes.sort_values("t", kind="stable")
    assert ordered["r"].tolist() == [10.0, 20.0, 15.0, 30.0, 25.0]  # t_start + t: 1001, 1002, 1002.5, 1003, 1003.5
    assert episodes["cause"].fillna("").tolist() == ["distance", "", "visibility", "collision", ""]


def test_plot_training_writes_png(tmp_path):
    path = training_plots.plot_training(_monitors(tmp_path), tmp_path / "training.png")
    _assert_png(path, 900, 650)


def test_training_figure_rolling_mean_and_stacked_causes(tmp_path):
    top, bottom = training_plots.training_figure(_monitors(tmp_path), window=2).axes
    (mean_line,) = top.get_lines()
    np.testing.assert_allclose(mean_line.get_xdata(), [100, 300, 450, 750, 3750])  # cumulative steps
    np.testing.assert_allclose(mean_line.get_ydata(), [10.0, 15.0, 17.5, 22.5, 27.5])
    counts = {bars.get_label(): sum(patch.get_height() for patch in bars) for bars in bottom.containers}
    assert counts == {"distance": 1, "visibility": 1, "collision": 1, training_plots.TIME_LIMIT: 2}
    assert {text.get_text() for text in bottom.get_legend().get_texts()} == set(counts)


def test_training_figure_shows_each_evaluation_with_its_spread(tmp_path):
    evaluations = pd.DataFrame({"num_timesteps": [200, 3000], "mean_return": [12.0, 40.0], "std_return": [1.0, 5.0]})
    top, _ = training_plots.training_figure(_monitors(tmp_path), window=2, evaluations=evaluations).axes
    (points,) = [c for c in top.containers if c.get_label() == "evaluation (mean, sd)"]
    line, _, (bars,) = points
    np.testing.assert_allclose(line.get_xdata(), [200, 3000])
    np.testing.assert_allclose(line.get_ydata(), [12.0, 40.0])
    spans = [segment[:, 1] for segment in bars.get_segments()]
    np.testing.assert_allclose(spans, [[11.0, 13.0], [35.0, 45.0]])
    with pytest.raises(ValueError, match="evaluations table"):
        training_plots.training_figure(_monitors(tmp_path), evaluations=pd.DataFrame({"steps": [1]}))


def test_training_figure_from_dataframe_without_cause():
    frame = pd.DataFrame({"r": np.linspace(-100, 100, 30), "l": 1000})
    top, bottom = training_plots.training_figure(frame, window=10).axes
    assert top.get_lines()[0].get_ydata()[-1] == pytest.approx(np.linspace(-100, 100, 30)[-10:].mean())
    assert {text.get_text() for text in bottom.get_legend().get_texts()} == {training_plots.TIME_LIMIT}
    assert sum(patch.get_height() for patch in bottom.patches) == 30
