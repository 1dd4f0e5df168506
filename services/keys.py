"""Key expressions of one swimm run, all under a namespace (default ``swimm/default``).

Step pipeline (pub/sub)::

    <ns>/<channel>/<env>/action            learner -> sim
    <ns>/<channel>/<env>/obs/<route>       sim -> encoder <route>, or -> learner when route is "direct"
    <ns>/<channel>/<env>/latent            encoder -> learner
    <ns>/<channel>/<env>/err               any service -> sender: refusals with their reason

Groups of envs stepped as one (``<group>`` named by the learner that drives them)::

    <ns>/<channel>/groups/<group>/action       learner -> sim: a BatchMsg of the group's actions
    <ns>/<channel>/groups/<group>/obs/<route>  sim -> encoder <route> (or learner, "direct"): their observations
    <ns>/<channel>/groups/<group>/latent       encoder -> learner: their latents

Control and presence::

    <ns>/<channel>/<env>/ctl               queryable: claim, release, reset, seed, info
    <ns>/@live/<role>/<id>                 liveliness tokens
    <ns>/metrics/<role>/<id>               periodic counters

The observation key carries its route so each frame reaches exactly one
encoder: an encoder subscribes only to ``<ns>/*/*/obs/<its id>``. A live
viewer that wants every frame subscribes to ``.../obs/*``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

CHANNELS = ("train", "eval")
GROUPS = "groups"  # the key chunk of grouped steps; one key level deeper than an env's, so wildcards keep them apart
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_chunk(value: str, what: str) -> str:
    """Refuse ids that would change the meaning of a key expression (``/``, ``*``, ``$``...)."""
    if not _CHUNK.match(value):
        raise ValueError(f"{what} {value!r} may hold only letters, digits, '_', '.', and '-'")
    return value


@dataclass(frozen=True)
class Keys:
    namespace: str = "swimm/default"

    def _env(self, channel: str, env: str) -> str:
        return f"{self.namespace}/{channel}/{env}"

    def action(self, channel: str, env: str) -> str:
        return f"{self._env(channel, env)}/action"

    def obs(self, channel: str, env: str, route: str) -> str:
        return f"{self._env(channel, env)}/obs/{route}"

    def latent(self, channel: str, env: str) -> str:
        return f"{self._env(channel, env)}/latent"

    def err(self, channel: str, env: str) -> str:
        return f"{self._env(channel, env)}/err"

    def ctl(self, channel: str, env: str) -> str:
        return f"{self._env(channel, env)}/ctl"

    # A group's keys are an env's keys with ``groups/<group>`` in the env's place: one level deeper.
    def group_action(self, channel: str, group: str) -> str:
        return self.action(channel, f"{GROUPS}/{group}")

    def group_obs(self, channel: str, group: str, route: str) -> str:
        return self.obs(channel, f"{GROUPS}/{group}", route)

    def group_latent(self, channel: str, group: str) -> str:
        return self.latent(channel, f"{GROUPS}/{group}")

    def group_actions(self, channel: str) -> str:
        """Every group's actions on one channel (what a sim serving that channel listens to)."""
        return f"{self.namespace}/{channel}/{GROUPS}/*/action"

    def encoder_group_inbox(self, encoder_id: str) -> str:
        """Every group's observations routed to one encoder."""
        return f"{self.namespace}/*/{GROUPS}/*/obs/{encoder_id}"

    def parse_group_key(self, key: str) -> tuple[str, str]:
        """(channel, group) of a group key such as ``<ns>/train/groups/learner-1.0/obs/enc-1``."""
        parts = self._chunks(key)
        if len(parts) < 4 or parts[0] not in CHANNELS or parts[1] != GROUPS:
            raise ValueError(f"{key!r} is not a group key of namespace {self.namespace!r}")
        return parts[0], parts[2]

    def _chunks(self, key: str) -> list[str]:
        """The chunks of ``key`` after the namespace ([] for a key outside it)."""
        prefix = self.namespace + "/"
        return key[len(prefix) :].split("/") if key.startswith(prefix) else []

    def encoder_inbox(self, encoder_id: str) -> str:
        """Every observation routed to one encoder, whatever its channel and env."""
        return f"{self.namespace}/*/*/obs/{encoder_id}"

    def live(self, role: str, ident: str) -> str:
        return f"{self.namespace}/@live/{role}/{ident}"

    def live_role(self, role: str) -> str:
        return f"{self.namespace}/@live/{role}/*"

    def about(self, role: str, ident: str) -> str:
        """Where a service answers what it runs (an encoder: its CMVAE's path and hash)."""
        return f"{self.namespace}/@about/{role}/{ident}"

    def about_role(self, role: str) -> str:
        return f"{self.namespace}/@about/{role}/*"

    def metrics(self, role: str, ident: str) -> str:
        return f"{self.namespace}/metrics/{role}/{ident}"

    def all_metrics(self) -> str:
        return f"{self.namespace}/metrics/**"

    def parse_env_key(self, key: str) -> tuple[str, str]:
        """(channel, env) of a step-pipeline key such as ``<ns>/train/0/obs/enc-1``."""
        parts = self._chunks(key)
        if len(parts) < 3 or parts[0] not in CHANNELS:
            raise ValueError(f"{key!r} is not a step key of namespace {self.namespace!r}")
        return parts[0], parts[1]
