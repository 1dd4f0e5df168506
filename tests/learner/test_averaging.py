"""The averaged actor (learner_service/averaging.py) on real stable-baselines3 learners, and through `swimm learn`."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from stable_baselines3 import PPO, SAC

from learner_service.averaging import WARMUP, ActorAverage


def _sac() -> SAC:
    return SAC("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=50, batch_size=32, seed=0,
               policy_kwargs={"net_arch": [16, 16]})  # fmt: skip


def _weights(network: torch.nn.Module) -> list[torch.Tensor]:
    return [parameter.detach().clone() for parameter in network.parameters()]


def test_the_average_follows_every_optimizer_step_with_the_warm_up_decay() -> None:
    model = _sac()
    updates = 40
    expected = _weights(model.actor)
    steps = [0]

    def by_hand(*_) -> None:  # the same average, step by step, from the weights after each step
        steps[0] += 1
        weight = 1.0 - min(1.0 - 1.0 / updates, (1 + steps[0]) / (WARMUP + steps[0]))
        for average, parameter in zip(expected, model.actor.parameters(), strict=True):
            average.mul_(1 - weight).add_(parameter.detach(), alpha=weight)

    average = ActorAverage(model, updates)
    model.actor.optimizer.register_step_post_hook(by_hand)
    model.learn(150)
    assert average.updates == steps[0] == 100  # one actor update per step after learning_starts
    for mine, theirs in zip(average.average, expected, strict=True):
        torch.testing.assert_close(mine, theirs)


def test_swapped_in_acts_with_the_average_and_gives_the_live_weights_back() -> None:
    model = _sac()
    average = ActorAverage(model, 20)
    model.learn(200)
    live = _weights(model.actor)
    assert any(not torch.equal(a, b) for a, b in zip(average.average, live, strict=True))  # they have drifted apart
    with average.swapped_in():
        for parameter, value in zip(model.actor.parameters(), average.average, strict=True):
            assert torch.equal(parameter, value)
    for parameter, value in zip(model.actor.parameters(), live, strict=True):
        assert torch.equal(parameter, value)


def test_an_on_policy_learner_averages_its_whole_policy() -> None:
    model = PPO("MlpPolicy", gym.make("Pendulum-v1"), n_steps=64, batch_size=32, n_epochs=1, seed=0)
    average = ActorAverage(model, 10)
    model.learn(128)
    assert average.network is model.policy and average.updates == 4  # 2 rollouts x 2 minibatches


def test_a_horizon_below_one_update_is_refused() -> None:
    with pytest.raises(ValueError, match="actor-average.*>= 1"):
        ActorAverage(_sac(), 0)
    from learner_service.command import check
    from learner_service.learn_settings import LearnCommandSettings

    with pytest.raises(ValueError, match="--actor-average -1: must be >= 0"):
        check(LearnCommandSettings(actor_average=-1))


@pytest.mark.filterwarnings("ignore:.*unbounded.*")
def test_swimm_learn_evaluates_and_saves_the_average_and_checkpoints_the_live_weights(tmp_path) -> None:
    from learner_service.command import Training
    from learner_service.learn_settings import EvalSettings, LearnCommandSettings

    settings = LearnCommandSettings(
        algo="sac", obs="state", backend="inprocess", steps=400, max_steps=100, seed=3, actor_average=50,
        hyperparams="{learning_starts: 100, batch_size: 32, train_freq: 1, gradient_steps: 1}",
        eval=EvalSettings(min_steps=1, every=400, unit="steps", episodes=1, max_steps=50),
        checkpoint_every=400, save_replay_buffer=False, run_dir=str(tmp_path), progress_bar=False,
    )  # fmt: skip
    Training(settings).run()
    final, best, live = (  # best: the average at the one evaluation (400 steps); live: the weights then
        torch.cat([p.detach().flatten() for p in SAC.load(path).actor.parameters()])
        for path in (tmp_path / "final_model.zip", tmp_path / "best_model.zip",
                     tmp_path / "checkpoints" / "model_400_steps.zip")
    )  # fmt: skip
    # SB3 trains once more after the last rollout, which moves the average by a few percent of one live update.
    assert torch.dist(final, best) < 0.2 * torch.dist(live, best)
    # The learner's own weights at the end, beside the average, to resume from: one update past the checkpoint.
    live_end = torch.cat([p.detach().flatten() for p in SAC.load(tmp_path / "final_model_live.zip").actor.parameters()])
    assert torch.dist(live_end, live) < torch.dist(live_end, final)
