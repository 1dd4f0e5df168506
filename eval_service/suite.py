"""`swimm eval --suite`: every contender in every held-out split, and the encoder's reading of each.

    swimm eval --suite --algo sac --checkpoint learner_service/models/sac_cmvae_robust.zip \\
        --algo scripted-camera --algo scripted --encoder-checkpoint encoder_service/models/cmvae_robust.pt \\
        --episodes 3 --seed 127 --out runs/suite

The splits are sim_service.splits' (``--suite-splits`` picks some), played after two references inside the
training range, clean and murky frames, so each split's drop is read against them. Every contender plays the same
episodes (same seeds) in every condition, on one env: a live sim's eval env (each reset carries the condition, so
the sim's other envs are untouched) or an in-process world. Beside the policies, the encoder named by
``--encoder-checkpoint`` (default: the shipped CMVAE; a pod detector reads too) reads ``--suite-frames`` reset
frames of each condition in process: its d, theta and psi errors say whether a failing split is perception or
control.

The run folder holds ``suite.csv`` (one row per contender and condition), ``encoder.csv`` (one row per
condition), ``episodes.csv`` (one row per episode: the per-episode returns an interval needs), ``suite.json``
(all of it with its provenance: command, commit, model hashes, seeds, host) and ``suite.png``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from encoder_service.inference import open_encoder
from encoder_service.model import label_errors
from eval_service.engine import (
    EvaluationSettings,
    cmvae_in_use,
    contenders,
    load_policies,
    play_plan,
    run_provenance,
    vertical_columns,
    with_policy_encoder,
)
from learner_service.task import episode_seed
from services.results import write_result
from sim_service.noise import PRESETS, NoiseSettings
from sim_service.settings import WorldSettings
from sim_service.splits import Split, resolve_splits

log = logging.getLogger(__name__)

#: Conditions inside the training range, played first so each split's drop has its reference.
REFERENCES = (
    Split("clean", "clean frames (in training)", NoiseSettings()),
    Split("murky", "the murky preset (in training)", PRESETS["murky"]),
)
SUITE_COLUMNS = ("label", "condition", "mean_return", "std_return", "A", "D", "A'", "D'", "C'", "S_D", "S_A",
                 "violations", "episodes")  # fmt: skip
ENCODER_COLUMNS = ("condition", "frames", "d_mae_m", "theta_mae_deg", "psi_mae_deg", "d_bias_m")


@dataclass
class SuiteSettings:
    """What a suite plays (the flags ``--suite-*``; ``--suite`` itself turns it on)."""

    splits: list[str] = field(default_factory=lambda: ["all"])  # which splits (sim_service.splits), or all
    frames: int = 200  # reset frames per condition the CMVAE reads for its d/theta/psi errors (0: none)


def suite_conditions(suite: SuiteSettings) -> list[Split]:
    """The references, then the chosen splits, in play order."""
    return [*REFERENCES, *resolve_splits(list(suite.splits))]


def check_suite(suite: SuiteSettings) -> None:
    """Refuse a suite that could only fail later, naming the setting."""
    suite_conditions(suite)
    if suite.frames < 0:
        raise ValueError(f"--suite-frames must be >= 0 (0: no encoder check), got {suite.frames}")


def run_suite(settings: EvaluationSettings, suite: SuiteSettings, out: Path) -> pd.DataFrame:
    """Play every contender in every condition, read each condition's frames with the CMVAE; write the folder."""
    settings = with_policy_encoder(settings)
    conditions = suite_conditions(suite)
    entries = contenders(settings)
    policies = load_policies(settings, entries)
    plan = [({"condition": split.name}, split.reset_options()) for split in conditions]
    rows, episodes, wall_s = play_plan(settings, entries, policies, plan, desc="suite")
    table = pd.DataFrame(rows, columns=[*SUITE_COLUMNS, *vertical_columns(settings)])
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "suite.csv", index=False)  # the play's results first: the encoder's reads come after
    pd.DataFrame(episodes).to_csv(out / "episodes.csv", index=False)
    encoder = encoder_errors(settings, conditions, suite.frames)
    encoder.to_csv(out / "encoder.csv", index=False)
    about = run_provenance(settings, entries, cmvae_reads=suite.frames > 0)
    record = {"rows": rows, "encoder": encoder.to_dict("records"), "episodes": episodes, "wall_s": wall_s,
              "conditions": [{"name": s.name, "about": s.about, **s.reset_options()} for s in conditions],
              "contenders": [vars(entry) for entry in entries]}  # fmt: skip
    write_result(out / "suite.json", record, about)
    if settings.figures:
        suite_figure(table, encoder).savefig(out / "suite.png", dpi=100)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    if not encoder.empty:
        print(encoder.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"run folder: {out}")
    return table


def encoder_errors(settings: EvaluationSettings, conditions: list[Split], count: int) -> pd.DataFrame:
    """MAE of the CMVAE's d, theta and psi on ``count`` reset frames of each condition (and d's mean signed
    error: unseen water has pulled distance readings one way)."""
    if count == 0:
        return pd.DataFrame(columns=list(ENCODER_COLUMNS))
    from sim_service.dataset import labels_and_pose  # MuJoCo: not in the torch image, which attaches only
    from sim_service.world import World

    encoder = open_encoder(cmvae_in_use(settings))
    world = World(WorldSettings())
    seeds = [episode_seed(settings.seed, frame) for frame in range(1, count + 1)]
    rows = []
    try:
        for split in conditions:
            frames, labels = [], []
            for seed in seeds:
                noise = split.noise if split.noise.enabled else False
                telemetry, frame = world.reset(seed, noise=noise, scene=split.scene)
                frames.append(frame)
                labels.append(labels_and_pose(telemetry)[0])
            mu, _ = encoder.encode(np.stack(frames))
            predicted = np.stack(encoder.decode_state(mu), axis=1)
            true = np.stack(labels)
            errors = label_errors(predicted, true).mean(axis=0)
            rows.append({"condition": split.name, "frames": len(seeds), "d_mae_m": float(errors[0]),
                         "theta_mae_deg": float(errors[1]), "psi_mae_deg": float(errors[2]),
                         "d_bias_m": float((predicted[:, 0] - true[:, 0]).mean())})  # fmt: skip
            log.info("encoder, %s: d %.2f m (bias %+.2f), theta %.2f deg, psi %.1f deg", split.name,
                     errors[0], rows[-1]["d_bias_m"], errors[1], errors[2])  # fmt: skip
    finally:
        world.close()
    return pd.DataFrame(rows, columns=list(ENCODER_COLUMNS))


def suite_figure(table: pd.DataFrame, encoder: pd.DataFrame) -> Figure:
    """Bars per condition: each contender's mean return (hatched where an episode had a violation), then the
    encoder's d and theta errors."""
    conditions = list(dict.fromkeys(table["condition"]))
    labels = list(dict.fromkeys(table["label"]))
    panels = 1 + (0 if encoder.empty else 2)
    fig = Figure(figsize=(max(6.0, 1.1 * len(conditions)), 2.8 * panels))
    axes = fig.subplots(panels, 1, squeeze=False)[:, 0]
    x = np.arange(len(conditions))
    width = 0.8 / max(len(labels), 1)
    for index, label in enumerate(labels):
        part = table[table["label"] == label].set_index("condition").reindex(conditions)
        bars = axes[0].bar(x + (index - (len(labels) - 1) / 2) * width, part["mean_return"], width,
                           label=str(label), color=f"C{index % 10}")  # fmt: skip
        for bar, violated in zip(bars, part["violations"].fillna(0) > 0, strict=True):
            if violated:
                bar.set_hatch("//")
    axes[0].set_ylabel("mean return")
    axes[0].set_title("Held-out splits (hatched: an episode lost the dolphin, left the band or collided)", fontsize=9)
    axes[0].legend(fontsize=7, ncol=min(len(labels), 4))
    if not encoder.empty:
        part = encoder.set_index("condition").reindex(conditions)
        for ax, column, unit in ((axes[1], "d_mae_m", "d MAE (m)"), (axes[2], "theta_mae_deg", "theta MAE (deg)")):
            ax.bar(x, part[column], 0.6, color="0.5")
            ax.set_ylabel(unit)
    for ax in axes:
        ax.set_xticks(x, conditions, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        ax.margins(x=0.02)
    axes[-1].set_xlabel("condition (clean and murky are inside the training range)")
    fig.tight_layout()
    return fig
