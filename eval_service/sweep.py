"""`swimm eval --sweep`: robustness curves, every contender played across image-noise severities or delays.

    swimm eval --sweep --backend inprocess --algo sac --checkpoint a.zip --algo scripted --episodes 2 \\
        --sweep-preset harsh --sweep-severities 0 0.5 1 1.5 2 --out runs/sweep
    swimm eval --sweep --sweep-kind latency --sweep-delays-ms 0 80 160 300 --sweep-rates-hz 50 25 10 ...

A condition is one group of effects (one effect alone, or ``all`` of them) at one severity: the preset's strength
of those effects times the severity, every other effect off (:func:`sim_service.noise.scaled`). Severity 0 is
clean frames, the same condition for every group, so it is played once. Every contender plays the same episodes
(the same seeds) in every condition, on one env: a live sim's eval env (each episode's reset carries the
condition's noise settings, so the sim's other envs are untouched; the claimed env keeps the last condition's
noise) or an in-process world.

With ``--sweep-kind latency`` the conditions are loop delays (``delay``: each action reaches the thrusters that
many milliseconds after the observation it answers, rounded to whole 20 ms steps) and control rates (``rate``: one
action per 50/Hz steps, held in between), each alone (sim_service.latency); the ``severity`` column holds the
milliseconds or the hertz. The delay is applied to the action: for a policy that answers what it observes, a
frame k steps late and an action k steps late make the same loop, and a ground-truth contender, which reads no
frames, meets the same delay as a camera one.

The run folder holds ``sweep.csv`` (one row per contender and condition: Table 12's columns), ``episodes.csv``
(one row per episode), ``sweep.json`` (the rows and how the run was made) and ``sweep.png`` (return and the
share of episodes with a violation, against severity, one panel per effect group).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import pandas as pd
from matplotlib.figure import Figure

from eval_service.engine import (
    EvaluationSettings,
    contenders,
    load_policies,
    play_plan,
    run_provenance,
    vertical_columns,
    with_policy_encoder,
)
from services.results import write_result
from services.settings import to_dict
from sim_service.noise import EFFECTS, PRESETS, scaled
from sim_service.settings import WorldSettings

log = logging.getLogger(__name__)

ALL_EFFECTS = "all"
SWEEP_KINDS = ("noise", "latency")
DELAY, RATE = "delay", "rate"
AXIS_LABELS = {DELAY: "loop delay (ms)", RATE: "control rate (Hz)"}
SWEEP_COLUMNS = ("label", "effects", "severity", "mean_return", "std_return", "A", "D", "A'", "D'", "C'", "S_D",
                 "S_A", "violations", "episodes")  # fmt: skip


@dataclass
class SweepSettings:
    """What a sweep plays (the flags ``--sweep-*``; ``--sweep`` itself turns it on)."""

    preset: str = "harsh"  # the preset whose effects the sweep scales (severity 1 = the preset)
    severities: list[float] = field(default_factory=lambda: [0.0, 0.5, 1.0, 1.5, 2.0])  # x preset; 0 = clean
    effects: list[str] = field(default_factory=lambda: [ALL_EFFECTS, *EFFECTS])  # each alone, and all together
    kind: Literal["noise", "latency"] = "noise"  # noise: effects x severities; latency: delays, control rates
    delays_ms: list[float] = field(default_factory=lambda: [0.0, 40.0, 80.0, 120.0, 160.0, 200.0, 300.0])
    rates_hz: list[float] = field(default_factory=lambda: [50.0, 25.0, 10.0])  # latency sweep: control rates


def check_sweep(plan: SweepSettings) -> None:
    """Refuse a sweep that could only fail later, naming the setting."""
    if plan.kind not in SWEEP_KINDS:
        raise ValueError(f"--sweep-kind must be one of {', '.join(SWEEP_KINDS)}, got {plan.kind!r}")
    if plan.kind == "latency":
        latency_steps(plan)
    if plan.preset not in PRESETS or plan.preset == "off":
        choices = ", ".join(name for name in PRESETS if name != "off")
        raise ValueError(f"--sweep-preset must be one of {choices}, got {plan.preset!r}")
    unknown = [name for name in plan.effects if name != ALL_EFFECTS and name not in EFFECTS]
    if unknown or not plan.effects:
        raise ValueError(f"--sweep-effects takes {ALL_EFFECTS} and {', '.join(EFFECTS)}; got {plan.effects}")
    if not plan.severities or any(s < 0 for s in plan.severities):
        raise ValueError(f"--sweep-severities must be numbers >= 0, got {plan.severities}")


def latency_steps(plan: SweepSettings) -> list[tuple[str, float, dict[str, int]]]:
    """(``delay`` ms or ``rate`` Hz, value, latency settings as a reset's map) of a latency sweep, checked."""
    step_ms = 1000 * WorldSettings().physics_dt  # the sims' default step
    if not plan.delays_ms and not plan.rates_hz:
        raise ValueError("a latency sweep needs --sweep-delays-ms or --sweep-rates-hz")
    played: list[tuple[str, float, dict[str, int]]] = []
    for ms in plan.delays_ms:
        if ms < 0:
            raise ValueError(f"--sweep-delays-ms must be >= 0, got {ms}")
        played.append((DELAY, ms, {"action_delay": round(ms / step_ms)}))
    for hz in plan.rates_hz:
        period = round(1000 / (hz * step_ms)) if hz > 0 else 0
        if period < 1 or not math.isclose(period * hz * step_ms, 1000, rel_tol=1e-6):
            raise ValueError(f"--sweep-rates-hz must divide the sim's {1000 / step_ms:g} Hz (50, 25, 10...), got {hz}")
        played.append((RATE, hz, {"control_period": period}))
    return played


def conditions(plan: SweepSettings) -> list[tuple[str, float, dict[str, Any]]]:
    """(group, severity, reset options) in play order. Noise: severity 0 once, as ``none``; latency: each
    condition alone (the others at none)."""
    if plan.kind == "latency":
        return [(group, value, {"latency": latency}) for group, value, latency in latency_steps(plan)]
    preset = PRESETS[plan.preset]
    played: list[tuple[str, float, dict[str, Any]]] = []
    severities = sorted(set(plan.severities))
    if 0.0 in severities:
        played.append(("none", 0.0, {"noise": dataclasses.asdict(scaled(preset, 0.0))}))
    for group in plan.effects:
        effects = EFFECTS if group == ALL_EFFECTS else (group,)
        for severity in severities:
            if severity > 0:
                played.append((group, severity, {"noise": dataclasses.asdict(scaled(preset, severity, effects))}))
    return played


def sweep(settings: EvaluationSettings, plan: SweepSettings, out: Path) -> pd.DataFrame:
    """Play every contender in every condition; write the run folder; returns the per-condition table."""
    settings = with_policy_encoder(settings)
    entries = contenders(settings)
    policies = load_policies(settings, entries)
    played = [({"effects": group, "severity": severity}, options) for group, severity, options in conditions(plan)]
    rows, episodes, wall_s = play_plan(settings, entries, policies, played, desc="sweep")
    table = pd.DataFrame(rows, columns=[*SWEEP_COLUMNS, *vertical_columns(settings)])
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "sweep.csv", index=False)
    pd.DataFrame(episodes).to_csv(out / "episodes.csv", index=False)
    record = {"rows": rows, "preset": dataclasses.asdict(PRESETS[plan.preset]),
              "contenders": [vars(entry) for entry in entries], "wall_s": wall_s,
              "settings": to_dict(settings), "argv": sys.argv}  # fmt: skip
    write_result(out / "sweep.json", record, run_provenance(settings, entries))
    if settings.figures:
        sweep_figure(table, plan.preset, kind=plan.kind).savefig(out / "sweep.png", dpi=100)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"run folder: {out}")
    return table


def sweep_figure(table: pd.DataFrame, preset: str, per_row: int = 5, kind: str = "noise") -> Figure:
    """Return and share of episodes with a violation against severity: a pair of panels per effect group, ``per_row``
    groups to a row. The clean condition (``none``) is every group's severity-0 point.
    """
    groups = [group for group in table["effects"].drop_duplicates() if group != "none"] or ["none"]
    clean = table[table["effects"] == "none"]
    margin = 0.05 * max(float(table["mean_return"].max() - table["mean_return"].min()), 1.0)
    returns = (float(table["mean_return"].min()) - margin, float(table["mean_return"].max()) + margin)  # one scale
    columns = min(per_row, len(groups))
    rows = math.ceil(len(groups) / columns)
    fig = Figure(figsize=(2.8 * columns, 4.4 * rows))
    axes = fig.subplots(2 * rows, columns, sharex=kind == "noise", squeeze=False)  # delays and rates: own axes
    for index, group in enumerate(groups):
        top, bottom = axes[2 * (index // columns), index % columns], axes[2 * (index // columns) + 1, index % columns]
        part = pd.concat([clean, table[table["effects"] == group]]).drop_duplicates()
        for colour, (label, played) in enumerate(part.groupby("label", sort=False)):
            played = played.sort_values("severity")
            style = {"color": f"C{colour % 10}", "marker": "o", "markersize": 3, "linewidth": 1.2}
            top.plot(played["severity"], played["mean_return"], label=str(label), **style)
            bottom.plot(played["severity"], played["violations"], **style)
        top.set_ylim(*returns)
        top.set_title(group, fontsize=9)
        top.set_ylabel("mean return", fontsize=8)
        bottom.set_ylabel("violation share", fontsize=8)
        bottom.set_ylim(-0.05, 1.05)
        bottom.set_xlabel(AXIS_LABELS.get(group, f"severity (x {preset})"), fontsize=8)
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    for index in range(len(groups), rows * columns):  # empty slots of the last row
        axes[2 * (index // columns), index % columns].set_visible(False)
        axes[2 * (index // columns) + 1, index % columns].set_visible(False)
    axes[0, 0].legend(fontsize=7)
    title = {"noise": "Robustness to image noise: each effect alone, and all together",
             "latency": "Robustness to a slow loop: delay and control rate, each alone"}[kind]  # fmt: skip
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
