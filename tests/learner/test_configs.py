"""Every shipped `swimm up` recipe (learner_service/configs/*.yaml) loads and passes the learner's checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from learner_service.command import check
from learner_service.up import UpSettings, sim_shares
from services import settings as settings_mod
from services.cli import build_parser, config_file

CONFIGS = sorted((Path(__file__).parents[2] / "learner_service" / "configs").glob("*.yaml"))


@pytest.mark.parametrize("config", CONFIGS, ids=[path.stem for path in CONFIGS])
def test_a_shipped_recipe_is_valid(config: Path) -> None:
    args = build_parser("up").parse_args(["up", "--config", str(config)])
    settings = settings_mod.load(UpSettings, args, config_file("up", args.config), environ={})
    check(settings.learn)
    sim_shares(settings.learn.envs, settings.sims)
    assert settings.learn.algo == config.stem.split("_")[0]  # sac_scratch.yaml trains sac
