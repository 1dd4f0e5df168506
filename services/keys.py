"""Key expressions of one swimm run, all under a namespace (default ``swimm/default``).

Step pipeline (pub/sub), each message a BatchMsg of a group of envs (services/messages.py)::

    <ns>/<channel>/<group>/action          learner -> sim
    <ns>/<channel>/<group>/obs/<route>     sim -> encoder <route>, or -> learner when route is "direct"
    <ns>/<channel>/<group>/latent          encoder -> learner

``<group>`` is named by the learner that steps it: the env's id for a single env (a group of one), and
``<holder>.<k>`` for several. A reset's observation goes out as its env's group of one (the reset request names
no group), so a learner listens on its own group's keys and on each of its envs'.

Control and presence::

    <ns>/<channel>/<env>/ctl               queryable: claim, release, reset, info
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
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_chunk(value: str, what: str) -> str:
    """Refuse ids that would change the meaning of a key expression (``/``, ``*``, ``$``...)."""
    if not _CHUNK.match(value):
        raise ValueError(f"{what} {value!r} may hold only letters, digits, '_', '.', and '-'")
    return value


@dataclass(frozen=True)
class Keys:
    namespace: str = "swimm/default"

    def _group(self, channel: str, group: str) -> str:
        return f"{self.namespace}/{channel}/{group}"

    def action(self, channel: str, group: str) -> str:
        return f"{self._group(channel, group)}/action"

    def obs(self, channel: str, group: str, route: str) -> str:
        return f"{self._group(channel, group)}/obs/{route}"

    def latent(self, channel: str, group: str) -> str:
        return f"{self._group(channel, group)}/latent"

    def actions(self, channel: str) -> str:
        """Every group's actions on one channel (what a sim serving that channel listens to)."""
        return self.action(channel, "*")

    def ctl(self, channel: str, env: str) -> str:
        return f"{self.namespace}/{channel}/{env}/ctl"

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

    def parse_step_key(self, key: str) -> tuple[str, str]:
        """(channel, group) of a step-pipeline key such as ``<ns>/train/0/obs/enc-1``."""
        parts = self._chunks(key)
        if len(parts) < 3 or parts[0] not in CHANNELS:
            raise ValueError(f"{key!r} is not a step key of namespace {self.namespace!r}")
        return parts[0], parts[1]
