"""Demonstrations from the scripted tracker: a head start for a learner that must see only the camera.

The scripted tracker (:mod:`learner_service.scripted`) steers from ground truth, which a deployed rover does
not have; the learner steers from its own observation (the CMVAE latent and ActPrev). Before training, the
tracker plays ``steps`` env steps on the training envs, and what it did is used in these ways:

- every transition (the learner's observation, the action taken, reward, next observation) goes into an
  off-policy learner's replay buffer, so its critic starts from episodes that track instead of episodes that
  lose the dolphin within a second;
- the learner's policy is fitted to the tracker's actions from the learner's own observations by regression
  (behaviour cloning), so its first episodes already follow the dolphin;
- an off-policy learner's critic then trains alone on that buffer for ``critic_steps`` gradient steps, the
  actor held still. Otherwise the first actor updates follow a random critic and undo the cloning within an
  episode or two;
- with ``bc_weight`` > 0, every later actor update keeps that cloning loss (:func:`keep_cloning`), since the
  warmed-up critic's action gradient can still lead the actor away from the tracker.

Then the learner trains as usual. Ground truth is used at training time only, like the reward; the trained
policy acts on its observation alone. The observations and clean actions are saved in the run folder
(:data:`DEMOS_FILE`), so a run resumed from one of its models keeps the same cloning loss without playing the
tracker again (:func:`resume_cloning`).

The actions taken carry Gaussian noise (``noise``, default 0.3) while the regression targets are the tracker's
clean actions. Without it the observation's ActPrev (the last ten actions) predicts the next action almost
exactly, and the cloned policy learns to repeat its last action instead of reading the latent. The noise also
spreads the buffer's actions around the tracker's, which the critic needs to rank actions. docs/benchmarks.md
(demonstrations) has the measurements behind each of these choices.
"""

from __future__ import annotations

import copy
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from learner_service.learn_settings import DemoSettings
from learner_service.progress import DEMOS_FILE, RunProgress
from learner_service.registry import Policy, deterministic_action

log = logging.getLogger(__name__)
#: Critic warm-up updates per call of the learner's ``train``, counted between calls; a multiple of the target
#: and policy update intervals (``gradient_step % interval`` restarts at each call), so the updates are the same.
CRITIC_CHUNK = 100


@dataclass(frozen=True)
class Demonstrations:
    """What the tracker showed: the learner's observations, the tracker's clean actions, the episodes' returns."""

    observations: np.ndarray  # (n, *obs_shape)
    actions: np.ndarray  # (n, action_size), the tracker's actions before noise: the regression targets
    returns: list[float]  # of the episodes that ended while it played


def save_demonstrations(demos: Demonstrations, path: Path) -> None:
    """One .npz: ``actions``, ``returns`` and ``observations`` (or ``observations.<key>`` for dict observations)."""
    if isinstance(demos.observations, dict):
        observations = {f"observations.{key}": value for key, value in demos.observations.items()}
    else:
        observations = {"observations": demos.observations}
    np.savez(path, actions=demos.actions, returns=np.asarray(demos.returns, dtype=np.float64), **observations)


def load_demonstrations(path: Path) -> Demonstrations:
    with np.load(path) as arrays:
        keyed = {name.split(".", 1)[1]: arrays[name] for name in arrays.files if name.startswith("observations.")}
        observations = keyed or arrays["observations"]
        return Demonstrations(observations, arrays["actions"], [float(r) for r in arrays["returns"]])


def innermost(env: VecEnv) -> VecEnv:
    """The VecEnv under its wrappers: demonstrations bypass the VecMonitor so the training CSV holds training."""
    while isinstance(env, VecEnvWrapper):
        env = env.venv
    return env


def play_tracker(
    model: Any, env: VecEnv, settings: DemoSettings, seed: int, teacher: Policy, progress: RunProgress | None = None
) -> Demonstrations:
    """Play ``teacher`` for ``settings.steps`` env steps, storing each transition in the model's buffer.

    The ground-truth tracker needs the telemetry in ``info`` (TrackingEnv and ProxyEnv put it there). A model
    without a replay buffer (on-policy) keeps only the observations and actions for :func:`clone_actions`.
    """
    progress = progress or RunProgress()
    progress.start("demonstrations", settings.steps)
    rng = np.random.default_rng(seed)
    env = innermost(env)
    buffer = getattr(model, "replay_buffer", None)
    obs = env.reset()
    infos = list(env.reset_infos)
    observations, actions, returns = [], [], []
    running = np.zeros(env.num_envs)
    for played in range(env.num_envs, settings.steps + env.num_envs, env.num_envs):
        clean = np.stack([teacher.act(_row(obs, i), info) for i, info in enumerate(infos)])
        taken = np.clip(clean + rng.normal(0.0, settings.noise, clean.shape), -1.0, 1.0).astype(np.float32)
        next_obs, rewards, dones, step_infos = env.step(taken)
        observations.append(obs)
        actions.append(clean)
        if buffer is not None:
            store(buffer, model.policy.scale_action(taken), obs, next_obs, rewards, dones, step_infos)
        running += rewards
        for index in np.flatnonzero(dones):
            returns.append(float(running[index]))
            running[index] = 0.0
        # After an automatic reset the next action answers the new episode's first telemetry.
        infos = [env.reset_infos[i] if dones[i] else info for i, info in enumerate(step_infos)]
        obs = next_obs
        progress.advance(played)
        if played % max(settings.steps // 10, 1) < env.num_envs:  # a line per tenth
            log.info("demonstrations: %d/%d steps, %d episodes ended", played, settings.steps, len(returns))
    return Demonstrations(_concat(observations), np.concatenate(actions), returns)


def store(buffer: Any, actions: np.ndarray, obs: Any, next_obs: Any, rewards: Any, dones: Any, infos: list) -> None:
    """One VecEnv step into a replay buffer (its public ``add``), as an off-policy learner stores its own: an env
    that just reset returned its new episode's first observation, so its transition ends in the terminal one."""
    ended = copy.deepcopy(next_obs)
    for index in np.flatnonzero(dones):
        terminal = infos[index].get("terminal_observation")
        if terminal is None:
            continue
        if isinstance(ended, dict):
            for key in ended:
                ended[key][index] = terminal[key]
        else:
            ended[index] = terminal
    buffer.add(obs, ended, actions, rewards, dones, infos)


def _row(observations: Any, index: int) -> Any:
    """One env's observation out of a VecEnv's batch (dict observations key by key)."""
    if isinstance(observations, dict):
        return {key: value[index] for key, value in observations.items()}
    return observations[index]


def _concat(batches: list[Any]) -> Any:
    if isinstance(batches[0], dict):
        return {key: np.concatenate([batch[key] for batch in batches]) for key in batches[0]}
    return np.concatenate(batches)


def clone_actions(
    model: Any, demos: Demonstrations, settings: DemoSettings, seed: int, progress: RunProgress | None = None
) -> list[float]:
    """Fit the policy's deterministic action to the tracker's by mean squared error; the loss of each epoch.

    Works for any stable-baselines3 policy whose deterministic action is differentiable (SAC, TD3, PPO, A2C): only the
    parameters on the action's path receive gradients, so a critic is left as it is. A TD3-style target actor is
    synced to the fitted actor.
    """
    progress = progress or RunProgress()
    progress.start("cloning", settings.bc_epochs)
    policy = model.policy
    policy.set_training_mode(True)
    parameters = [p for p in policy.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=settings.bc_learning_rate)
    targets = torch.as_tensor(demos.actions, dtype=torch.float32, device=policy.device)
    count = len(targets)
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for epoch in range(settings.bc_epochs):
        order = torch.randperm(count, generator=generator).numpy()
        total = 0.0
        for start in range(0, count, settings.bc_batch_size):
            rows = order[start : start + settings.bc_batch_size]
            loss = cloning_loss(policy, demos, targets, rows)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += loss.item() * len(rows)
        losses.append(total / count)
        progress.advance(epoch + 1)
        log.info("behaviour cloning epoch %d/%d: action MSE %.4f", epoch + 1, settings.bc_epochs, losses[-1])
    policy.set_training_mode(False)
    if hasattr(model, "actor_target"):
        model.actor_target.load_state_dict(model.actor.state_dict())
    return losses


def cloning_loss(policy: Any, demos: Demonstrations, targets: torch.Tensor, rows: np.ndarray) -> torch.Tensor:
    """Mean squared error between the policy's deterministic actions and the tracker's, on demonstration ``rows``."""
    obs_tensor, _ = policy.obs_to_tensor(_rows(demos.observations, rows))
    return torch.nn.functional.mse_loss(deterministic_action(policy, obs_tensor), targets[rows])


def _rows(observations: Any, rows: np.ndarray) -> Any:
    if isinstance(observations, dict):
        return {key: value[rows] for key, value in observations.items()}
    return observations[rows]


def train_critic(model: Any, gradient_steps: int, progress: RunProgress | None = None) -> None:
    """The off-policy learner's own ``train`` with every actor parameter frozen: the critic (and an automatic
    entropy coefficient) learn the value of the cloned policy from the buffer while the policy stays as cloned.

    An actor parameter without ``requires_grad`` gets no gradient, and its optimizer skips it. ``train`` runs in
    chunks of :data:`CRITIC_CHUNK` updates (the same updates, one after another) so ``progress`` can count them.
    """
    progress = progress or RunProgress()
    progress.start("critic warm-up", gradient_steps)
    frozen = [p for p in model.actor.parameters() if p.requires_grad]
    for parameter in frozen:
        parameter.requires_grad_(False)
    try:
        model.logger  # noqa: B018 (train() records its losses; `swimm learn` sets the run's logger before this)
    except AttributeError:
        model.set_logger(Logger(folder=None, output_formats=[]))
    try:
        for done in range(0, gradient_steps, CRITIC_CHUNK):
            model.train(gradient_steps=min(CRITIC_CHUNK, gradient_steps - done), batch_size=model.batch_size)
            progress.advance(min(done + CRITIC_CHUNK, gradient_steps))
    finally:
        for parameter in frozen:
            parameter.requires_grad_(True)
    log.info("critic trained for %d gradient steps with the cloned actor held", gradient_steps)


def keep_cloning(model: Any, demos: Demonstrations, settings: DemoSettings, seed: int) -> Any:
    """Add ``bc_weight`` times the cloning loss on a demonstration minibatch to every actor update from now on.

    The learner's own ``train`` stays untouched: a hook on the actor's optimizer adds the cloning gradient to
    the one the learner's loss left, just before each step (the TD3+BC idea). Measured on the CMVAE that learns
    psi: without it, SAC's first 64 updates after the critic's warm-up undo the cloned policy (docs/encoder.md).
    Returns the hook's handle (``.remove()`` ends it).
    """
    policy = model.policy
    targets = torch.as_tensor(demos.actions, dtype=torch.float32, device=policy.device)
    rng = np.random.default_rng(seed)

    def add_cloning_gradient(optimizer: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
        rows = rng.integers(len(targets), size=settings.bc_batch_size)
        (settings.bc_weight * cloning_loss(policy, demos, targets, rows)).backward()

    return model.actor.optimizer.register_step_pre_hook(add_cloning_gradient)


def demonstrate(
    model: Any,
    env: VecEnv,
    settings: DemoSettings,
    seed: int,
    run_dir: Path,
    teacher: Policy,
    progress: RunProgress | None = None,
) -> Demonstrations:
    """Play the teacher, fill the buffer, clone its actions, train the critic: the whole head start, logged, each
    part a phase of ``progress``.

    The demonstrations are saved as ``run_dir/`` :data:`DEMOS_FILE` for :func:`resume_cloning`.
    """
    demos = play_tracker(model, env, settings, seed, teacher, progress)
    mean = f"{np.mean(demos.returns):.1f}" if demos.returns else "n/a"
    log.info("tracker played %d steps, %d episodes ended (mean return %s)", len(demos.actions), len(demos.returns),
             mean)  # fmt: skip
    if settings.bc_epochs:
        clone_actions(model, demos, settings, seed, progress)
    if settings.critic_steps and hasattr(model, "replay_buffer") and hasattr(model, "actor"):
        train_critic(model, settings.critic_steps, progress)
    save_demonstrations(demos, run_dir / DEMOS_FILE)
    if settings.bc_weight > 0 and hasattr(model, "actor"):
        keep_cloning(model, demos, settings, seed)
        log.info("actor updates keep a cloning loss of weight %g", settings.bc_weight)
    return demos


def resume_cloning(model: Any, settings: DemoSettings, seed: int, resumed_from: Path, run_dir: Path) -> bool:
    """A resumed run's head start: the kept cloning loss again, on the demonstrations of the run it resumes.

    The buffer, the cloned actor and the critic come back with the model (and its saved replay buffer); only
    the cloning loss needs the demonstrations, looked for beside the model and in its run folder (a checkpoint
    sits in ``<run>/checkpoints/``) and copied into ``run_dir``. Returns whether the loss is kept.
    """
    if settings.bc_weight <= 0 or not hasattr(model, "actor"):
        return False
    found = next((p for p in (resumed_from.parent / DEMOS_FILE, resumed_from.parent.parent / DEMOS_FILE)
                  if p.is_file()), None)  # fmt: skip
    if found is None:
        log.warning(
            "resuming without the kept cloning loss: no %s beside %s or in its run folder (bc_weight %g asks for it)",
            DEMOS_FILE,
            resumed_from,
            settings.bc_weight,
        )
        return False
    if found.resolve() != (run_dir / DEMOS_FILE).resolve():
        shutil.copyfile(found, run_dir / DEMOS_FILE)
    keep_cloning(model, load_demonstrations(found), settings, seed)
    log.info("resumed: actor updates keep a cloning loss of weight %g on the demonstrations of %s",
             settings.bc_weight, found)  # fmt: skip
    return True
