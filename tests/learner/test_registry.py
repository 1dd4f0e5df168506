"""Learner registry: tuned defaults reach the SB3 models, import paths work, bad names fail clearly, policies load.

The models train on a tiny gymnasium env built from the TrackingTask's own spaces (no sim): the registry's job
is wiring hyperparameters and classes, which does not need physics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

from learner_service.learn_settings import TrackerGains
from learner_service.registry import (
    Policy,
    SB3Policy,
    algorithm_names,
    load_hyperparams,
    load_policy,
    make_model,
)
from learner_service.scripted import ScriptedTracker
from learner_service.task import TaskSettings, TrackingTask

EPISODE_STEPS = 8


class TaskSpacesEnv(gym.Env):
    """Observations drawn from a TrackingTask's observation space; reward is highest for (surge, yaw) = (0.5, 0)."""

    def __init__(self, obs_mode: str = "cmvae") -> None:
        task = TrackingTask(TaskSettings(obs=obs_mode))
        self.observation_space = task.observation_space
        self.action_space = task.action_space
        self._steps = 0

    def _observe(self) -> Any:
        if isinstance(self.observation_space, gym.spaces.Dict):
            return {
                "image": self.np_random.integers(0, 256, (64, 64, 3), dtype=np.uint8),
                "actions": self.np_random.uniform(-1, 1, 20).astype(np.float32),
            }
        return self.np_random.uniform(-1, 1, self.observation_space.shape).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        self._steps = 0
        return self._observe(), {}

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict]:
        self._steps += 1
        reward = -float((action[0] - 0.5) ** 2 + action[1] ** 2)
        return self._observe(), reward, False, self._steps >= EPISODE_STEPS, {}


def test_named_algorithms() -> None:
    assert algorithm_names() == ["ppo", "sac", "scripted", "scripted-camera", "td3"]
    assert load_hyperparams("sac")["n_timesteps"] == 1_000_000


def test_sac_carries_the_tuned_values() -> None:
    model = make_model("sac", TaskSpacesEnv(), seed=97, overrides={"device": "cpu"})
    assert model.learning_rate == pytest.approx(7.3e-4)
    assert model.buffer_size == 300_000
    assert model.learning_starts == 500
    assert model.batch_size == 256
    assert model.tau == pytest.approx(0.02)
    assert model.gamma == pytest.approx(0.99)
    assert model.train_freq == TrainFreq(1, TrainFrequencyUnit.EPISODE)
    assert model.gradient_steps == 64
    assert model.ent_coef == "auto" and model.log_ent_coef is not None
    assert model.use_sde and model.sde_sample_freq == 64 and model.use_sde_at_warmup
    layers = [m for m in model.policy.actor.latent_pi if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in layers] == [(30, 64), (64, 64)]
    np.testing.assert_allclose(model.policy.actor.log_std.detach().numpy(), -2.0)
    assert model.seed == 97


def test_td3_carries_the_tuned_values() -> None:
    model = make_model("td3", TaskSpacesEnv(), seed=101, overrides={"device": "cpu", "buffer_size": 10_000})
    assert model.learning_rate == pytest.approx(1e-3)
    assert model.batch_size == 256 and model.tau == pytest.approx(0.005)
    assert model.train_freq == TrainFreq(512, TrainFrequencyUnit.STEP)
    assert model.gradient_steps == 64
    assert model.policy_delay == 2
    assert model.target_policy_noise == pytest.approx(0.2) and model.target_noise_clip == pytest.approx(0.5)
    assert isinstance(model.action_noise, OrnsteinUhlenbeckActionNoise)
    np.testing.assert_allclose(model.action_noise._sigma, [0.5, 0.5])
    layers = [m for m in model.policy.actor.mu if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in layers] == [(30, 400), (400, 300), (300, 2)]
    assert load_hyperparams("td3")["model"]["buffer_size"] == 1_000_000  # the override did not touch the defaults


def pink_td3(seed: int, n_envs: int) -> Any:
    env = make_vec_env(TaskSpacesEnv, n_envs=n_envs, seed=seed)
    overrides = {"device": "cpu", "buffer_size": 1000, "learning_starts": 16, "train_freq": [8, "step"],
                 "gradient_steps": 1, "action_noise": {"type": "pink", "sigma": 0.3, "seq_len": 64}}  # fmt: skip
    return make_model("td3", env, seed=seed, overrides=overrides)


def noise_draws(seed: int, n_envs: int, steps: int = 64) -> np.ndarray:
    """A pink-noise TD3's exploration noise over ``steps`` steps: (time, env, action)."""
    noise = pink_td3(seed, n_envs).action_noise
    return np.stack([noise() for _ in range(steps)])


def test_pink_action_noise_is_per_env_seeded_and_slow() -> None:
    draws = noise_draws(seed=5, n_envs=3)
    np.testing.assert_array_equal(draws, noise_draws(seed=5, n_envs=3))  # reproducible from the model's seed
    other = noise_draws(seed=6, n_envs=3)
    assert not np.allclose(draws, other)
    assert draws.shape == (64, 3, 2)
    assert not np.allclose(draws[:, 0], draws[:, 1]) and not np.allclose(draws[:, 1], draws[:, 2])
    # pink noise drifts: consecutive draws are correlated, as white noise's are not
    lag_one = [np.corrcoef(draws[:-1, env, k], draws[1:, env, k])[0, 1] for env in range(3) for k in range(2)]
    assert np.mean(lag_one) > 0.3


def test_td3_trains_with_pink_noise_on_several_envs() -> None:
    model = pink_td3(seed=7, n_envs=2)
    model.learn(64)
    assert model.num_timesteps == 64
    with pytest.raises(ValueError, match="seq_len >= 2 and sigma > 0"):
        make_model("td3", TaskSpacesEnv(), seed=0, overrides={"action_noise": {"type": "pink", "sigma": 0}})
    with pytest.raises(ValueError, match="unknown action noise 'brown'.*normal, pink"):
        make_model("td3", TaskSpacesEnv(), seed=0, overrides={"action_noise": {"type": "brown"}})


def test_action_noise_takes_one_scale_per_action_dimension() -> None:
    def noise(spec: dict[str, Any]) -> Any:
        return make_model("td3", TaskSpacesEnv(), seed=0, overrides={"device": "cpu", "buffer_size": 1000,
                                                                       "action_noise": spec}).action_noise  # fmt: skip

    np.testing.assert_allclose(noise({"type": "ornstein_uhlenbeck", "sigma": [0.3, 0.05]})._sigma, [0.3, 0.05])
    surge_only = noise({"type": "normal", "sigma": [0.3, 0.0]})
    draws = np.stack([surge_only() for _ in range(200)])
    assert np.all(draws[:, 1] == 0.0) and 0.2 < draws[:, 0].std() < 0.4  # yaw held still, surge explored
    for bad, message in (([0.3, 0.1, 0.1], "a list of 2 numbers"), ("wide", "a list of 2 numbers"),
                         ([0.3, -0.1], "finite and >= 0"), ([float("nan"), 0.1], "finite and >= 0")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            noise({"type": "normal", "sigma": bad})


def test_ppo_carries_the_tuned_values() -> None:
    model = make_model("ppo", TaskSpacesEnv(), seed=103, overrides={"device": "cpu"})
    assert model.lr_schedule(1.0) == pytest.approx(1e-4)
    assert model.lr_schedule(0.5) == pytest.approx(5e-5)  # linear to 0 over training
    assert model.n_steps == 512 and model.batch_size == 128 and model.n_epochs == 10
    assert model.gae_lambda == pytest.approx(0.95) and model.clip_range(1.0) == pytest.approx(0.2)
    assert model.ent_coef == 0.0 and model.vf_coef == pytest.approx(0.5) and model.max_grad_norm == pytest.approx(0.5)
    assert model.use_sde and model.sde_sample_freq == 4
    assert model.policy.ortho_init is False
    assert model.policy.activation_fn is torch.nn.GELU
    pi = [m for m in model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    vf = [m for m in model.policy.mlp_extractor.value_net if isinstance(m, torch.nn.Linear)]
    assert [m.out_features for m in pi] == [256, 256] and [m.out_features for m in vf] == [256, 256]


def test_overrides_merge_policy_kwargs_key_by_key() -> None:
    model = make_model("sac", TaskSpacesEnv(), seed=1, overrides={"device": "cpu", "policy_kwargs": {"net_arch": [8]}})
    layers = [m for m in model.policy.actor.latent_pi if isinstance(m, torch.nn.Linear)]
    assert [m.out_features for m in layers] == [8]
    np.testing.assert_allclose(model.policy.actor.log_std.detach().numpy(), -2.0)  # still the YAML's


SMALL_OFF_POLICY = {"learning_starts": 16, "gradient_steps": 2, "batch_size": 16, "buffer_size": 1000}
FAST_TRAINING = {
    "sac": SMALL_OFF_POLICY,
    "td3": {**SMALL_OFF_POLICY, "train_freq": [8, "step"]},
    "ppo": {"n_steps": 32, "batch_size": 16, "n_epochs": 1},
}


@pytest.mark.parametrize("algo", sorted(FAST_TRAINING))
def test_train_save_and_load_a_deterministic_policy(algo: str, tmp_path: Path) -> None:
    env = TaskSpacesEnv()
    model = make_model(algo, env, seed=7, overrides={"device": "cpu", **FAST_TRAINING[algo]})
    model.learn(64)
    assert model.num_timesteps == 64
    model.save(tmp_path / algo)
    policy = load_policy(algo, tmp_path / f"{algo}.zip", device="cpu")
    assert isinstance(policy, SB3Policy) and isinstance(policy, Policy)
    obs, _ = env.reset(seed=3)
    action = policy.act(obs, {})
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
    np.testing.assert_allclose(action, model.predict(obs, deterministic=True)[0], atol=1e-6)
    np.testing.assert_array_equal(policy.act(obs, {}), action)  # deterministic


def test_any_sb3_api_class_by_import_path_with_a_dict_observation() -> None:
    env = TaskSpacesEnv("image")
    model = make_model("stable_baselines3:A2C", env, seed=5, overrides={"device": "cpu", "n_steps": 4})
    assert type(model).__name__ == "A2C"
    assert type(model.policy).__name__ == "MultiInputActorCriticPolicy"
    model.learn(8)
    assert model.num_timesteps == 8


def test_bad_names_fail_clearly(tmp_path: Path) -> None:
    env = TaskSpacesEnv()
    with pytest.raises(ValueError, match="unknown algorithm 'dqnx'.*ppo, sac, scripted, scripted-camera, td3"):
        make_model("dqnx", env, seed=0)
    with pytest.raises(ValueError, match="cannot import module 'no_such_package.algos'"):
        make_model("no_such_package.algos:Fast", env, seed=0)
    with pytest.raises(ValueError, match="has no class 'Missing'"):
        make_model("stable_baselines3:Missing", env, seed=0)
    with pytest.raises(ValueError, match="does not follow the stable-baselines3 API"):
        make_model("collections:OrderedDict", env, seed=0)
    for scripted in ("scripted", "scripted-camera"):
        with pytest.raises(ValueError, match="nothing to train"):
            make_model(scripted, env, seed=0)
    with pytest.raises(ValueError, match="not a torch.nn module class"):
        make_model("ppo", env, seed=0, overrides={"policy_kwargs": {"activation_fn": "Swishy"}})
    with pytest.raises(ValueError, match="bad schedule"):
        make_model("ppo", env, seed=0, overrides={"learning_rate": "lin_fast"})
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_policy("sac", tmp_path / "missing.zip")
    with pytest.raises(ValueError, match="needs a checkpoint"):
        load_policy("sac", None)


def test_scripted_needs_no_checkpoint() -> None:
    policy = load_policy("scripted", None)
    assert isinstance(policy, ScriptedTracker) and isinstance(policy, Policy)
    with pytest.raises(ValueError, match="info\\['telemetry'\\]"):
        policy.act(np.zeros(30), {})


def test_scripted_trackers_take_the_gains_they_are_given() -> None:
    gains = TrackerGains(yaw_gain=1 / 90, yaw_damping=1.5)
    assert load_policy("scripted", None, gains=gains).gains == gains
    assert load_policy("scripted-camera", None, gains=gains).gains == gains  # the shipped CMVAE's decoders
    assert load_policy("scripted", None).gains == TrackerGains()
