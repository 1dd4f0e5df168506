"""The tracking env over Zenoh: the learner's Gymnasium env whose step is action -> sim (-> encoder) -> reply.

:class:`ProxyEnv` is the distributed twin of :class:`learner_service.inprocess_env.TrackingEnv`: the same
:class:`TrackingTask` turns the remote world's telemetry (and the encoder's latent, or the raw frame) into
observations, rewards and terminations, with the same episode seeds and the same time limit, so the two are
interchangeable and a seed gives the same trajectory either way. Only the transport differs, and that is
:class:`learner_service.link.EnvLink`'s job (idempotent retries, duplicate dropping, routing to an encoder, a
timeout that names the missing service); a ProxyEnv steps on a link of its own env (a group of one).

:class:`ProxyVecEnv` drives several remote envs from one session as a stable-baselines3 ``VecEnv``, over links
of ``group_size`` envs each (one by default): ``step_async`` sends every link's actions before ``step_wait``
gathers the replies, so the sim and the encoder work on all environments' steps while the learner waits, rather
than one round trip after the other.

Episode numbers: ``info["ep"]`` counts the task's episodes from 1 (it restarts when ``reset(seed=...)``
restarts the seed sequence), as in-process. The episode number on the wire is a separate counter that only
grows, starting after the sim's current episode, because the sim refuses to go back to an earlier one.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import zenoh
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvObs, VecEnvStepReturn

from learner_service.link import EnvLink, SimAction, StepRefused, new_holder_id
from learner_service.task import (
    CAUSE_SIM_LOST,
    LATENCY_OPTION,
    NOISE_OPTION,
    SCENE_OPTION,
    Frame,
    TaskSettings,
    TrackingTask,
    episode_seed,
)
from services.control import CLAIMANT_ROLES, ControlError
from services.keys import CHANNELS, Keys, check_chunk
from services.lifecycle import Owner
from services.messages import refused_as_unclaimed
from services.presence import Roster, announce
from services.session import open_session
from services.settings import ZenohSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimLost:
    """In place of a reply: the sim refused the step because it no longer knows the env (it restarted)."""

    refusal: str


def sim_lost(refusal: StepRefused) -> SimLost:
    """The refusal as a lost episode, or raised again if it is any other refusal."""
    if not refused_as_unclaimed(refusal):
        raise refusal
    return SimLost(str(refusal))


def own_session(owner: Owner, proxy: ProxySettings) -> zenoh.Session:
    """A session of the owner's own, closed with it (one it is lent is its lender's to close)."""
    return owner.resources.enter_context(open_session(proxy.zenoh, role=proxy.role))


class ClaimRefused(ControlError):
    """The env could not be claimed: another holder has it (named in the message), or no sim serves it."""


@dataclass
class ProxySettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    channel: str = "train"  # "train" | "eval"
    envs: tuple[str, ...] = ("0",)  # env ids on that channel
    step_timeout_s: float = 2.0  # wait per try before re-sending the same (episode, seq)
    max_retries: int = 10  # re-sends before StepTimeout
    poll_ms: float = 0.0  # poll for each reply this long, then nap (services/polling.py)
    role: str = "learner"  # liveliness role of the holder: "learner" or "eval"
    group_size: int = 0  # envs stepped as one message each way (ProxyVecEnv); 0 or 1 = each env its own messages

    def check(self) -> None:
        """Refuse settings that could only fail later, with a message that says what to change."""
        if self.channel not in CHANNELS:
            raise ValueError(f"channel must be one of {CHANNELS}, got {self.channel!r}")
        if self.role not in CLAIMANT_ROLES:
            raise ValueError(f"role must be one of {CLAIMANT_ROLES} (whose claims the sim lapses), not {self.role!r}")
        if not self.envs:
            raise ValueError("envs must name at least one env id")
        for env in self.envs:
            check_chunk(env, "env id")
        if self.step_timeout_s <= 0 or self.max_retries < 0:
            raise ValueError("step_timeout_s must be > 0 and max_retries >= 0")
        if self.group_size < 0:
            raise ValueError(f"group_size must be >= 0 (0: no groups), got {self.group_size}")


class Presence(Owner):
    """A learner's stand in the namespace: its holder id and liveliness token, the encoder roster in cmvae mode,
    and the links it steps over, made and closed together (by a ProxyEnv, or by a ProxyVecEnv for all its envs)."""

    def __init__(self, session: zenoh.Session, keys: Keys, proxy: ProxySettings, encoded: bool, name: str) -> None:
        self.session, self.keys, self.proxy, self.encoded = session, keys, proxy, encoded
        self.holder = new_holder_id(proxy.role)
        self.encoders: Roster | None = None
        self.resources.enter_context(announce(session, keys, proxy.role, self.holder))
        if encoded:
            self.encoders = self.resources.enter_context(Roster(session, keys, "encoder"))
            if not self.encoders.members():
                wait_s = proxy.zenoh.startup_timeout_s
                log.info("%s: waiting up to %.0f s for a live encoder", name, wait_s)
                try:
                    self.encoders.wait_for(1, timeout_s=wait_s)
                except BaseException:
                    self.close()
                    raise

    def link(self, envs: list[str], group: str = "") -> EnvLink:
        proxy = self.proxy
        link = EnvLink(self.session, self.keys, proxy.channel, envs, self.holder, self.encoded, self.encoders,
                       proxy.step_timeout_s, proxy.max_retries, proxy.poll_ms, group)  # fmt: skip
        self.resources.callback(link.close)
        return link


class ProxyEnv(Owner, gym.Env):
    """Gymnasium env of the tracking task on a remote sim; ``info`` as TrackingEnv's (telemetry, cause, d, theta,
    azimuth, psi, ep, and seed at reset).

    Construction claims the env (:class:`ClaimRefused` names the holder if it is taken), and in cmvae mode waits,
    bounded by ``zenoh.startup_timeout_s`` and logged, for a live encoder. A step that gets no reply after every
    retry raises :class:`learner_service.link.StepTimeout` naming the missing service. ``close()`` releases the
    env, and the liveliness token this env holds means the sim frees it anyway if this process dies.
    """

    metadata = {"render_modes": ["rgb_array"]}
    render_mode = (
        "rgb_array"  # render(): the last camera frame the sim sent (None before the first, or if it sends none)
    )

    def __init__(
        self,
        task: TaskSettings,
        proxy: ProxySettings,
        env: str | None = None,
        base_seed: int = 0,
        session: zenoh.Session | None = None,
        member: tuple[EnvLink, int] | None = None,
    ) -> None:
        """``member``: env ``index`` of a link its vector env owns (with its holder and token), else a link of its
        own for env ``env`` (default: ``proxy.envs[0]``)."""
        proxy.check()
        self.task = TrackingTask(task)
        self.observation_space = self.task.observation_space
        self.action_space = self.task.action_space
        self.proxy = proxy
        self.env_id = check_chunk(member[0].envs[member[1]] if member else env or proxy.envs[0], "env id")
        self.base_seed = base_seed
        self.episode = 0
        self._last_image: np.ndarray | None = None
        self.keys = Keys(proxy.zenoh.namespace)
        self.session = session if session is not None else own_session(self, proxy)
        self._link: EnvLink | None = None
        self.index = 0
        self._pending_action: np.ndarray | None = None
        self._last_obs: Any = None
        self._last_info: dict[str, Any] = {}
        self.sims_lost = 0  # episodes cut short because the sim restarted and forgot them
        try:
            if member is None:
                presence = Presence(self.session, self.keys, proxy, self.task.settings.obs == "cmvae", self.name)
                member = (self.resources.enter_context(presence).link([self.env_id]), 0)
            self._link, self.index = member
            self.holder = self._link.holder
            wait_s = proxy.zenoh.startup_timeout_s
            log.info("%s: claiming as %s (waiting up to %.0f s for a sim that serves it)", self.name, self.holder,
                     wait_s)  # fmt: skip
            self._claim(wait_s)
        except BaseException:
            self.close()
            raise

    @property
    def name(self) -> str:
        return f"{self.proxy.channel}/{self.env_id}"

    def _claim(self, wait_s: float) -> None:
        try:
            claimed = self.link.claim(timeout_s=wait_s, index=self.index)
        except ControlError as exc:
            raise ClaimRefused(f"cannot claim env {self.name}: {exc}") from None
        # The next episode on the wire must come after the sim's current one.
        self.link.ep[self.index] = claimed.ep

    def _claim_again(self, refusal: str) -> None:
        """The sim forgot this env (it was restarted): claim it again, so the next reset starts a new episode."""
        self.sims_lost += 1
        log.warning("%s: the sim lost the episode (%s); claiming the env again", self.name, refusal)
        self._claim(self.proxy.zenoh.startup_timeout_s)

    # --- gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict[str, Any]]:
        """Next episode; a ``seed`` restarts the run's episode sequence at episode 1 of base seed ``seed``.

        ``options={"noise": True | False | {...}}`` switches the sim's image noise from this episode on (a map holds
        noise settings by name, e.g. ``{"preset": "murky"}``); ``{"latency": {...}}`` sets its camera and control
        delays (sim_service.latency) the same way, and ``{"scene": {...}}`` its scenery (sim_service.scenery).
        """
        super().reset(seed=seed)
        if seed is not None:
            self.base_seed, self.episode = seed, 0
        self.episode += 1
        world_seed = episode_seed(self.base_seed, self.episode)
        options = options or {}
        try:
            reply = self._start_episode(world_seed, options)
        except ControlError as exc:  # refused at once, or on a re-send after the sim restarted mid-reset
            if not refused_as_unclaimed(exc):
                raise
            self._claim_again(str(exc))
            reply = self._start_episode(world_seed, options)
        self._pending_action = None
        obs = self._last_obs = self.task.reset(self._frame(reply), seed=world_seed)
        info = self.task.info(reply.telemetry, self.task.settings.task)
        info = self._last_info = info | {"ep": self.episode, "seed": world_seed}
        log.debug("%s: episode %d (seed %d) starts at d %.2f m", self.name, self.episode, world_seed, info["d"])
        return obs, info

    def _start_episode(self, world_seed: int, options: dict) -> Frame:
        link = self.link
        link.send_reset(link.ep[self.index] + 1, world_seed, options.get(NOISE_OPTION), options.get(LATENCY_OPTION),
                        options.get(SCENE_OPTION), index=self.index)  # fmt: skip
        return link.wait()[0]

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        self.send_step(action)
        return self.finish_step()

    # --- the two halves of a step, for ProxyVecEnv ---------------------------------------------------
    def send_step(self, action: Any) -> None:
        """Send the action on this env's own link; the reply is collected by :meth:`finish_step`."""
        self.link.send([self.begin_step(action)])

    def begin_step(self, action: Any) -> SimAction:
        """Check the action and mark the step in flight; the sim's action, for the caller (or a group) to send."""
        if self.episode == 0:
            raise RuntimeError("call reset() before step()")
        if self._pending_action is not None:
            raise RuntimeError(f"{self.name}: a step is already in flight; finish it first")
        sim_action = self.task.to_sim_action(action)  # validates before anything is sent
        self._pending_action = np.asarray(action)
        return sim_action

    def finish_step(self, reply: Frame | SimLost | None = None) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """The step in flight, from ``reply`` (its link's, read by the vector env) or from waiting on this env's
        own link."""
        if self._pending_action is None:
            raise RuntimeError(f"{self.name}: no step in flight")
        try:
            reply = reply if reply is not None else self.link.wait()[0]
        except StepRefused as exc:
            reply = sim_lost(exc)
        if isinstance(reply, SimLost):
            # The episode is gone with the sim that held it: end it here, truncated (its return so far stands,
            # nothing after it is made up), and claim the env again so the next reset starts afresh.
            self._pending_action = None
            self._claim_again(reply.refusal)
            return self._last_obs, 0.0, False, True, self._last_info | {"ep": self.episode, "cause": CAUSE_SIM_LOST}
        action, self._pending_action = self._pending_action, None
        obs, reward, terminated, info = self.task.step(action, self._frame(reply))
        info |= {"ep": self.episode}
        self._last_obs, self._last_info = obs, info
        return obs, reward, terminated, self.task.time_up, info

    # --- helpers -------------------------------------------------------------------------------------
    @property
    def link(self) -> EnvLink:
        if self._link is None:
            raise RuntimeError(f"{self.name}: this env is closed")
        return self._link

    def _frame(self, reply: Frame) -> Frame:
        self._last_image = reply.image
        return reply

    def render(self) -> np.ndarray | None:
        """The last camera frame (uint8 RGB), kept out of ``info`` so SB3 does not copy it into every step's info."""
        return self._last_image

    @property
    def retries(self) -> int:
        """Re-sends so far (each one a lost or late reply bridged without losing or repeating a step)."""
        return self._link.retries if self._link is not None else 0

    def close(self) -> None:
        """Release the env, then close what it owns (its vector env owns a shared link); safe to call twice."""
        if self._link is not None:
            self._link.release(self.index)
            self._link = None
        super().close()


class ProxyVecEnv(Owner, VecEnv):
    """One :class:`ProxyEnv` per ``proxy.envs`` entry on one shared session, as a stable-baselines3 VecEnv.

    Its envs step over links of ``proxy.group_size`` envs (one each by default) and hold their claims under one
    holder id, the vector env's. ``step_async`` sends all actions at once and ``step_wait`` gathers the replies, so
    the remote steps overlap.
    SB3's auto-reset semantics hold (``info["terminal_observation"]``, ``info["TimeLimit.truncated"]``), and
    sub-env i has base seed ``base_seed + i``, exactly as a DummyVecEnv of TrackingEnvs would. A VecEnv of its
    own (the public base class only): the observations are stacked here, not in DummyVecEnv's private buffers.
    """

    def __init__(
        self,
        task: TaskSettings,
        proxy: ProxySettings,
        base_seed: int = 0,
        session: zenoh.Session | None = None,
    ) -> None:
        proxy.check()
        self.session = session if session is not None else own_session(self, proxy)
        self.envs: list[ProxyEnv] = []
        try:
            presence = Presence(self.session, Keys(proxy.zenoh.namespace), proxy, task.obs == "cmvae",
                                f"{proxy.channel}/{','.join(proxy.envs)}")  # fmt: skip
            self.links = self._make_links(self.resources.enter_context(presence), proxy)
            for link in self.links:
                for index in range(len(link.envs)):
                    member = ProxyEnv(task, proxy, base_seed=base_seed + len(self.envs), session=self.session,
                                      member=(link, index))  # fmt: skip
                    self.envs.append(self.resources.enter_context(member))
        except BaseException:
            self.close()
            raise
        super().__init__(len(self.envs), self.envs[0].observation_space, self.envs[0].action_space)

    @staticmethod
    def _make_links(presence: Presence, proxy: ProxySettings) -> list[EnvLink]:
        """Consecutive envs, ``group_size`` to a link (the last may be smaller): one env's link is named after it,
        a group's after this learner."""
        size, envs = max(proxy.group_size, 1), list(proxy.envs)
        links = [presence.link(envs[start : start + size], f"{presence.holder}.{start // size}" if size > 1 else "")
                 for start in range(0, len(envs), size)]  # fmt: skip
        for link in links:  # a vector step's messages spread over the encoders, not queued at one
            link.siblings = tuple(other.name for other in links)
        return links

    def reset(self) -> VecEnvObs:
        observations = []
        for index, env in enumerate(self.envs):
            options = {"options": self._options[index]} if self._options[index] else {}
            obs, self.reset_infos[index] = env.reset(seed=self._seeds[index], **options)
            observations.append(obs)
        self._reset_seeds()  # VecEnv's own: a seed or options given through seed()/set_options() apply once
        self._reset_options()
        return self._stack(observations)

    def step_async(self, actions: np.ndarray) -> None:
        """Every env's action goes out before any reply is awaited: one message per link."""
        sim_actions = [env.begin_step(action) for env, action in zip(self.envs, actions, strict=True)]
        start = 0
        for link in self.links:
            link.send(sim_actions[start : start + len(link.envs)])
            start += len(link.envs)

    def _replies(self) -> Iterator[Frame | SimLost]:
        """Each env's reply in env order; a link whose sim restarted gives each of its envs a :class:`SimLost`.

        A generator, so that ``step_wait`` turns one link's replies into observations (and resets its finished
        episodes) while the later links' steps are still with the sim and the encoder, rather than after all of them.
        """
        for link in self.links:
            try:
                yield from link.wait()
            except StepRefused as exc:
                yield from [sim_lost(exc)] * len(link.envs)

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = [], np.zeros(self.num_envs, np.float32), np.zeros(self.num_envs, bool), []
        for index, (env, reply) in enumerate(zip(self.envs, self._replies(), strict=True)):
            obs, rewards[index], terminated, truncated, info = env.finish_step(reply)
            dones[index] = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            if dones[index]:
                info["terminal_observation"] = obs
                obs, self.reset_infos[index] = env.reset()
            observations.append(obs)
            infos.append(info)  # each step's info is a new dict (TrackingTask.info): no copy needed
        return self._stack(observations), rewards, dones, infos

    def _stack(self, observations: list[Any]) -> VecEnvObs:
        if isinstance(observations[0], dict):
            return {key: np.stack([obs[key] for obs in observations]) for key in observations[0]}
        return np.stack(observations)

    def get_images(self) -> list[np.ndarray | None]:
        return [env.render() for env in self.envs]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.envs[i], attr_name) for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for i in self._get_indices(indices):
            setattr(self.envs[i], attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any):
        return [getattr(self.envs[i], method_name)(*method_args, **method_kwargs) for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [is_wrapped(self.envs[i], wrapper_class) for i in self._get_indices(indices)]
