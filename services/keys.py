"""Key expressions of one swimm run, all under a namespace (default ``swimm/default``).

Step pipeline (pub/sub)::

    <ns>/<channel>/<env>/action            learner -> sim
    <ns>/<channel>/<env>/obs/<route>       sim -> encoder <route>, or -> learner when route is "direct"
    <ns>/<channel>/<env>/latent            encoder -> learner
    <ns>/<channel>/<env>/err               any service -> sender: refusals with their reason

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

    def encoder_inbox(self, encoder_id: str) -> str:
        """Every observation routed to one encoder, whatever its channel and env."""
        return f"{self.namespace}/*/*/obs/{encoder_id}"

    def live(self, role: str, ident: str) -> str:
        return f"{self.namespace}/@live/{role}/{ident}"

    def live_role(self, role: str) -> str:
        return f"{self.namespace}/@live/{role}/*"

    def metrics(self, role: str, ident: str) -> str:
        return f"{self.namespace}/metrics/{role}/{ident}"

    def all_metrics(self) -> str:
        return f"{self.namespace}/metrics/**"

    def parse_env_key(self, key: str) -> tuple[str, str]:
        """(channel, env) of a step-pipeline key such as ``<ns>/train/0/obs/enc-1``."""
        prefix = self.namespace + "/"
        parts = key[len(prefix) :].split("/") if key.startswith(prefix) else []
        if len(parts) < 3 or parts[0] not in CHANNELS:
            raise ValueError(f"{key!r} is not a step key of namespace {self.namespace!r}")
        return parts[0], parts[1]

    @staticmethod
    def last_chunk(key: str) -> str:
        return key.rsplit("/", 1)[-1]
