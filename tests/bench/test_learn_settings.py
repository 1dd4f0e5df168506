"""What `swimm bench learn` hands each run's learner, and the mistakes it refuses before any run starts."""

from __future__ import annotations

import gymnasium as gym
import pytest

from bench.learn import learn_settings, run
from bench.learn_settings import LearnBenchSettings
from learner_service.command import Training
from learner_service.registry import merge_overrides, resolve_algorithm, resolve_kwargs


def test_hyperparams_reach_every_runs_learner_over_the_shipped_values(tmp_path) -> None:
    overrides = "{learning_rate: lin_7.3e-4}"
    settings = LearnBenchSettings(algos=["sac"], seeds=[97], hyperparams=overrides, out=str(tmp_path))
    learn = learn_settings(settings, "sac", 97)
    training = Training(learn)
    assert learn.obs == "cmvae" and learn.demo.steps == 0  # from scratch, camera only
    _, defaults = resolve_algorithm("sac")
    kwargs = resolve_kwargs(merge_overrides(defaults, training.overrides), gym.spaces.Box(-1, 1, (2,)))
    assert kwargs["learning_rate"](1.0) == pytest.approx(7.3e-4) and kwargs["learning_rate"](0.0) == 0.0
    assert kwargs["gradient_steps"] == defaults["gradient_steps"]  # the rest as shipped


def test_hyperparams_that_are_not_a_mapping_are_refused_before_the_first_run(tmp_path) -> None:
    out = tmp_path / "bench"
    settings = LearnBenchSettings(algos=["sac"], seeds=[97], hyperparams="[1, 2]", out=str(out))
    with pytest.raises(ValueError, match="--hyperparams must be a YAML mapping"):
        run(settings)
    assert not out.exists()
