"""Every shipped `swimm up` recipe (learner_service/configs/*.yaml) loads and passes the learner's checks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from learner_service.command import check, parse_hyperparams
from learner_service.up import UpSettings, sim_shares
from services import settings as settings_mod
from swimm.cli import build_parser, config_file

ROOT = Path(__file__).parents[2]
CONFIGS = sorted((ROOT / "learner_service" / "configs").glob("*.yaml"))
BENCH = ROOT / "docs" / "bench"
#: Each from-scratch recipe, the committed `swimm bench learn` run whose numbers its comment and docs/learner.md
#: quote, and the hyperparameters file that run read (None: the SPEC's).
MEASURED_BY = {
    "sac_scratch": ("learn-sac-caps-avg500-3seeds.json", None),
    "ppo_scratch": ("learn-ppo-smooth2-3seeds.json", None),
    "td3_scratch": ("learn-td3-g-3seeds.json", "learn-td3-g-hyperparams.yaml"),
}


def _load(config: Path) -> UpSettings:
    args = build_parser("up").parse_args(["up", "--config", str(config)])
    return settings_mod.load(UpSettings, args, config_file("up", args.config), environ={})


@pytest.mark.parametrize("config", CONFIGS, ids=[path.stem for path in CONFIGS])
def test_a_shipped_recipe_is_valid(config: Path) -> None:
    settings = _load(config)
    check(settings.learn)
    sim_shares(settings.learn.envs, settings.sims)
    assert settings.learn.algo == config.stem.split("_")[0]  # sac_scratch.yaml trains sac


@pytest.mark.parametrize("name", sorted(MEASURED_BY))
def test_a_from_scratch_recipe_is_the_run_its_numbers_come_from(name: str) -> None:
    record, hyperparams = MEASURED_BY[name]
    run = json.loads((BENCH / record).read_text())["settings"]
    settings = _load(ROOT / "learner_service" / "configs" / f"{name}.yaml")
    learn = settings.learn
    assert run["algos"] == [learn.algo]
    assert (run["budget_steps"], run["envs"], run["sims"]) == (learn.steps, learn.envs, settings.sims)
    assert (run["actor_average"], run["eval_every"]) == (learn.actor_average, learn.eval.every)
    smooth = run["smooth"]
    assert (smooth["temporal"], smooth["spatial"], smooth.get("bound", 0.0)) == (
        learn.smooth.temporal,
        learn.smooth.spatial,
        learn.smooth.bound,
    )
    expected = parse_hyperparams(str(BENCH / hyperparams)) if hyperparams else {}
    assert parse_hyperparams(learn.hyperparams) == expected
