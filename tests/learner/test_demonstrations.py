"""Demonstrations from the scripted tracker: the replay buffer, behaviour cloning, and `swimm learn --demo-steps`.

Real worlds and real SB3 models on state observations (no rendering), small step counts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from learner_service.command import Training, check
from learner_service.demonstrations import (
    Demonstrations,
    clone_actions,
    innermost,
    keep_cloning,
    load_demonstrations,
    play_tracker,
    save_demonstrations,
    train_critic,
)
from learner_service.envs import make_vec_env, shared_encoder
from learner_service.learn_settings import DemoSettings
from learner_service.progress import DEMOS_FILE, FINAL_MODEL
from learner_service.registry import LATENT_SCRIPTED, load_policy, make_model
from learner_service.scripted import ScriptedTracker
from learner_service.task import TaskSettings
from tests.learner.test_command import tiny_settings

pytestmark = pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")

TASK = TaskSettings(obs="state", max_steps=120)
DEMO_STEPS = 300


@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """A SAC model and two envs whose replay buffer holds DEMO_STEPS noisy tracker steps (with a monitor CSV)."""
    monitor = tmp_path_factory.mktemp("demo") / "train"
    env = make_vec_env("inprocess", TASK, n_envs=2, base_seed=97, monitor_path=monitor)
    model = make_model("sac", env, seed=97, overrides={"device": "cpu", "buffer_size": 1000})
    demos = play_tracker(model, env, DemoSettings(steps=DEMO_STEPS, noise=0.3), seed=5, teacher=ScriptedTracker())
    yield model, env, demos, monitor
    env.close()


def test_every_tracker_step_lands_in_the_replay_buffer_with_its_noisy_action(played) -> None:
    model, env, demos, _ = played
    buffer = model.replay_buffer
    stored = buffer.size() * env.num_envs  # the buffer counts rows of n_envs transitions
    assert stored == DEMO_STEPS == len(demos.actions)
    taken = buffer.actions[: buffer.size()].reshape(-1, 2)
    clean = demos.actions
    # the stored actions are the tracker's plus noise of std 0.3 (clipped to [-1, 1]), not the clean ones
    difference = taken - clean
    assert 0.2 < difference.std() < 0.35
    assert np.abs(taken).max() <= 1.0
    # the observations are the learner's own: state vector (12) + ActPrev (20)
    assert demos.observations.shape == (DEMO_STEPS, 32)
    np.testing.assert_array_equal(buffer.observations[: buffer.size()].reshape(-1, 32), demos.observations)


def test_the_clean_targets_are_what_the_tracker_does_on_the_same_episode(played) -> None:
    _, _, demos, _ = played
    fresh = make_vec_env("inprocess", TASK, n_envs=2, base_seed=97)  # same seeds: the same first episodes
    try:
        fresh.reset()
        first = [ScriptedTracker().act(None, info) for info in innermost(fresh).reset_infos]
    finally:
        fresh.close()
    np.testing.assert_allclose(demos.actions[:2], np.stack(first), rtol=0, atol=1e-6)
    assert not np.allclose(demos.actions[0], demos.actions[2])  # the targets follow the episode


def test_demonstrations_stay_out_of_the_training_monitor(played) -> None:
    _, _, demos, monitor = played
    assert demos.returns, "a 120-step time limit over 300 steps on 2 envs ends episodes"
    episodes = pd.read_csv(f"{monitor}.monitor.csv", skiprows=1)
    assert episodes.empty


def test_cloning_fits_the_policy_to_the_tracker(played) -> None:
    model, _, demos, _ = played

    def action_mse() -> float:
        predicted, _ = model.predict(demos.observations, deterministic=True)
        return float(np.mean((predicted - demos.actions) ** 2))

    before = action_mse()
    losses = clone_actions(model, demos, DemoSettings(bc_epochs=40, bc_batch_size=64), seed=0)
    after = action_mse()
    assert len(losses) == 40 and losses[-1] < losses[0] / 3
    assert after < before / 3, (before, after)


def test_critic_training_leaves_the_actor_as_cloned(played) -> None:
    model, _, _, _ = played
    actor = {name: value.clone() for name, value in model.actor.state_dict().items()}
    critic = {name: value.clone() for name, value in model.critic.state_dict().items()}
    train_critic(model, gradient_steps=20)
    assert all(torch.equal(actor[name], value) for name, value in model.actor.state_dict().items())
    assert any(not torch.equal(critic[name], value) for name, value in model.critic.state_dict().items())
    assert all(p.requires_grad for p in model.actor.parameters())  # unfrozen again for training


def test_a_kept_cloning_loss_holds_the_actor_near_the_tracker_through_training() -> None:
    """The same cloned SAC trained 200 gradient steps with and without ``bc_weight``: the weighted one stays closer."""

    def cloned_then_trained(bc_weight: float) -> tuple[float, float]:
        env = make_vec_env("inprocess", TASK, n_envs=2, base_seed=97)
        try:
            model = make_model("sac", env, seed=97, overrides={"device": "cpu", "buffer_size": 1000})
            settings = DemoSettings(steps=DEMO_STEPS, bc_epochs=40, bc_batch_size=64, bc_weight=bc_weight)
            demos = play_tracker(model, env, settings, seed=5, teacher=ScriptedTracker())
            clone_actions(model, demos, settings, seed=0)
            train_critic(model, gradient_steps=20)

            def action_mse() -> float:
                predicted, _ = model.predict(demos.observations, deterministic=True)
                return float(np.mean((predicted - demos.actions) ** 2))

            cloned = action_mse()
            handle = keep_cloning(model, demos, settings, seed=0) if bc_weight else None
            model.train(gradient_steps=200, batch_size=64)
            if handle is not None:
                handle.remove()
            return cloned, action_mse()
        finally:
            env.close()

    cloned, drifted = cloned_then_trained(0.0)
    same_start, held = cloned_then_trained(50.0)
    assert same_start == pytest.approx(cloned)  # same seeds: the same cloned policy before training
    assert drifted > 2 * cloned, (cloned, drifted)  # the critic's gradient alone leads the actor away
    assert held < drifted / 2, (held, drifted)


def test_bad_demo_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="--demo-steps -1: must be >= 0"):
        DemoSettings(steps=-1).check()
    with pytest.raises(ValueError, match="--demo-bc-weight -1.0: must be >= 0"):
        DemoSettings(bc_weight=-1.0).check()
    with pytest.raises(ValueError, match="--demo-bc-learning-rate 0.0: must be > 0"):
        DemoSettings(bc_learning_rate=0.0).check()


def test_a_camera_teacher_acts_on_the_learners_own_observation() -> None:
    """With the camera-only teacher every clean target is the latent tracker's action on the stored observation:
    a function of what the learner sees, so cloning can fit it exactly, noise or not."""
    task = TaskSettings(obs="cmvae", max_steps=60)
    encoder = shared_encoder(task)
    env = make_vec_env("inprocess", task, n_envs=1, base_seed=97, encoder=encoder)
    try:
        model = make_model("sac", env, seed=97, overrides={"device": "cpu", "buffer_size": 500})
        teacher = load_policy(LATENT_SCRIPTED, None)
        demos = play_tracker(model, env, DemoSettings(steps=80, noise=0.3), seed=5, teacher=teacher)
    finally:
        env.close()
    expected = np.stack([teacher.act(observation, {}) for observation in demos.observations])
    np.testing.assert_allclose(demos.actions, expected, rtol=0, atol=1e-6)
    ground_truth = make_vec_env("inprocess", task, n_envs=1, base_seed=97, encoder=encoder)
    try:
        ground_truth.reset()
        tracker_first = ScriptedTracker().act(None, innermost(ground_truth).reset_infos[0])
    finally:
        ground_truth.close()
    assert not np.allclose(demos.actions[0], tracker_first, atol=1e-4)  # it does not read the ground truth


def test_demo_teachers_are_checked_before_anything_starts(tmp_path) -> None:
    with pytest.raises(ValueError, match="demo teacher must be one of scripted, scripted-camera, got 'oracle'"):
        check(tiny_settings(tmp_path, demo=DemoSettings(steps=10, teacher="oracle")))
    with pytest.raises(ValueError, match="needs --obs cmvae, got state"):
        check(tiny_settings(tmp_path, demo=DemoSettings(steps=10, teacher=LATENT_SCRIPTED)))


def test_learn_with_demonstrations_starts_from_a_filled_buffer(tmp_path) -> None:
    settings = tiny_settings(tmp_path / "run", demo=DemoSettings(steps=150, bc_epochs=2, critic_steps=10))
    settings.eval.enabled = False
    training = Training(settings)
    result = training.run()
    assert result.trained_steps >= 200  # the demonstrations do not count as training steps
    episodes = pd.read_csv(tmp_path / "run" / "train.monitor.csv", skiprows=1)
    assert episodes["l"].sum() <= result.trained_steps  # the monitor holds training episodes only


def test_demonstrations_survive_a_save_and_load_exactly(played, tmp_path) -> None:
    _, _, demos, _ = played
    save_demonstrations(demos, tmp_path / "flat.npz")
    loaded = load_demonstrations(tmp_path / "flat.npz")
    assert np.array_equal(loaded.observations, demos.observations) and np.array_equal(loaded.actions, demos.actions)
    assert loaded.returns == demos.returns
    keyed = Demonstrations({"image": np.arange(24, dtype=np.uint8).reshape(2, 3, 4), "acts": np.ones((2, 5))},
                           demos.actions[:2], [])  # fmt: skip
    save_demonstrations(keyed, tmp_path / "dict.npz")
    loaded = load_demonstrations(tmp_path / "dict.npz")
    assert set(loaded.observations) == {"image", "acts"} and loaded.returns == []
    assert all(np.array_equal(loaded.observations[k], v) for k, v in keyed.observations.items())


def test_a_resumed_run_keeps_the_cloning_loss_on_the_first_runs_demonstrations(tmp_path, caplog) -> None:
    demo = DemoSettings(steps=150, bc_epochs=2, critic_steps=10, bc_weight=5.0)
    first = tiny_settings(tmp_path / "first", demo=demo)
    first.eval.enabled = False
    Training(first).run()
    assert (tmp_path / "first" / DEMOS_FILE).is_file()

    again = tiny_settings(tmp_path / "again", demo=demo, resume=str(tmp_path / "first" / FINAL_MODEL), steps=60)
    again.eval.enabled = False
    caplog.clear()  # the first run's lines, where an earlier test left INFO on
    with caplog.at_level("INFO", logger="learner_service.demonstrations"):
        resumed = Training(again).run()
    assert resumed.trained_steps >= 60
    assert "resumed: actor updates keep a cloning loss of weight 5" in caplog.text
    assert "tracker played" not in caplog.text  # the tracker did not play again
    copied = load_demonstrations(tmp_path / "again" / DEMOS_FILE)
    assert np.array_equal(copied.actions, load_demonstrations(tmp_path / "first" / DEMOS_FILE).actions)

    (tmp_path / "first" / DEMOS_FILE).unlink()
    (tmp_path / "again" / DEMOS_FILE).unlink()
    caplog.clear()
    with caplog.at_level("WARNING", logger="learner_service.demonstrations"):
        Training(again).run()
    assert "resuming without the kept cloning loss: no demonstrations.npz" in caplog.text


def test_the_shipped_policys_recipe_loads_as_swimm_up_settings() -> None:
    from learner_service.command import check, parse_hyperparams
    from learner_service.up import UpSettings
    from services import settings as settings_mod

    recipe = Path(__file__).resolve().parents[2] / "learner_service" / "models" / "sac_cmvae.yaml"
    up = settings_mod.load(UpSettings, None, recipe, environ={})
    check(up.learn)
    assert (up.learn.algo, up.learn.obs, up.learn.backend) == ("sac", "cmvae", "zenoh")
    assert up.learn.demo.steps > 0 and up.learn.demo.critic_steps > 0
    assert parse_hyperparams(up.learn.hyperparams)["policy_kwargs"]["log_std_init"] == -4.0


def test_the_noise_robust_recipe_names_files_that_ship() -> None:
    from learner_service.command import check
    from learner_service.up import UpSettings, encoder_checkpoint, learner_settings
    from services import settings as settings_mod

    root = Path(__file__).resolve().parents[2]
    up = settings_mod.load(UpSettings, None, root / "learner_service" / "models" / "sac_cmvae_robust.yaml", environ={})
    check(learner_settings(up, "tcp/127.0.0.1:7447", Path(".")))  # the learner it starts; its sim reads the file
    assert up.learn.demo.teacher == LATENT_SCRIPTED and up.learn.obs == "cmvae"
    assert encoder_checkpoint(up.learn).name == "cmvae_robust.pt"  # refuses a missing file
    sim = yaml.safe_load((root / up.learn.sim_config).read_text())
    assert sim["noise_randomise"] is True and sim["noise_preset"] == "murky"
    assert (root / "learner_service" / "models" / "sac_cmvae_robust.zip").is_file()


@pytest.mark.parametrize(
    ("recipe", "encoder", "noise"),
    [("sac_cmvae_3d", "cmvae_vertical.pt", None), ("sac_cmvae_3d_robust", "cmvae_vertical_robust.pt", "murky")],
)
def test_the_3d_recipes_load_as_swimm_learn_settings_on_the_encoder_their_policy_records(
    recipe, encoder, noise
) -> None:
    from learner_service.command import check
    from learner_service.identity import read_identity
    from learner_service.learn_settings import LearnCommandSettings
    from learner_service.up import encoder_checkpoint
    from services import settings as settings_mod
    from sim_service.settings import world_of_file

    root = Path(__file__).resolve().parents[2]
    models = root / "learner_service" / "models"
    learn = settings_mod.load(LearnCommandSettings, None, models / f"{recipe}.yaml", environ={})
    check(learn)
    assert (learn.task, learn.demo.teacher, learn.scripted.surge_gain) == ("3d", LATENT_SCRIPTED, 0.5)
    assert (learn.scripted.heave_gain, learn.scripted.heave_dead_band) == (0.2, 0.0)  # the teacher's firmer heave
    recorded = read_identity(models / f"{recipe}.zip")
    assert recorded["task"]["name"] == "3d" and recorded["encoder"]["path"] == learn.encoder_checkpoint
    assert encoder_checkpoint(learn).name == encoder
    assert (world_of_file(root / learn.sim_config).noise.preset if learn.sim_config else None) == noise
