"""Versioned msgpack messages of the step pipeline and the control plane, and their validation.

Every message is a msgpack map carrying the protocol version ``v`` and the
send time ``t`` (seconds, ``time.time()``); a step message (:class:`BatchMsg`)
adds its items, each an env with its episode ``ep``, step ``seq`` and fields,
a control request its ``op`` and a control reply ``ok``. Decoding validates shape and ranges and
raises :class:`BadMessage` with a reason a human can act on; services turn
that into a refusal and an error counter, never a crash.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

from services.telemetry import Telemetry

M = TypeVar("M")

#: 2: every step message is a BatchMsg of N items (a single env is a group of one), on the keys of the group it
#: steps; ErrorMsg and the err key are gone, a refusal travelling as its env's error item (docs/architecture.md).
#: 3: an item carries its message's fields as a map, not the message encoded on its own (one msgpack pass).
#: 4: telemetry carries a pod's identity ground truth (pod_size, followed, target_occluded; services/identity.py).
#: 5: a tracking encoder's prior travels with the env's messages (ActionMsg.prior, ObservationMsg.prior,
#: LatentMsg.next_prior), so the encoder keeps no state.
#: 6: the prior is a list of numbers, not one: any tracking encoder's state (an azimuth, an azimuth and a distance,
#: the pod tracker's tracks) travels as 5's azimuth did.
PROTOCOL_VERSION = 6
#: Payloads above this size are refused before decoding (a 1080p RGB frame is ~6.2 MB).
MAX_PAYLOAD_BYTES = 8 * 1024 * 1024
ACTION_SIZE = 4  # (sway, heave, surge, yaw)
#: A policy's action components by task (the learner's action space, an exported file's contract, what the pilot
#: flies): the planar curriculum drives surge and yaw, the 3d task heave too.
POLICY_ACTIONS: dict[str, tuple[str, ...]] = {"planar": ("surge", "yaw"), "3d": ("surge", "heave", "yaw")}
#: The most numbers a tracking encoder's prior may hold (the pod tracker's state holds 64).
MAX_PRIOR_SIZE = 256
#: A tracking encoder's state for one env's next frame, flattened; None where there is none (a new episode).
Prior = tuple[float, ...]
IMAGE_SHAPE = (64, 64, 3)  # the camera frame (H, W, RGB) the encoder reads and image policies observe
DIRECT_ROUTE = "direct"  # observation goes straight to the learner, no encoder
#: The words of a sim's refusal to drive an env nobody holds: a learner that reads them knows the sim lost its claim
#: (it restarted) and claims the env again.
UNCLAIMED = "is not claimed"


def refused_as_unclaimed(refusal: Exception) -> bool:
    """Whether a refusal says the sim no longer holds the env's claim (it restarted), so claiming again helps."""
    return UNCLAIMED in str(refusal)


class BadMessage(ValueError):
    """A message that cannot be accepted; ``str(exc)`` is the reason sent back."""


class DiveMode(StrEnum):
    MANUAL = "manual"
    STABILISE = "stabilise"
    DEPTH_HOLD = "depth_hold"


def _pack(body: dict[str, Any]) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def unpack(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode a payload into a map, checking size, format and protocol version."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise BadMessage(f"payload of {len(payload)} bytes exceeds the {MAX_PAYLOAD_BYTES}-byte limit")
    try:
        body = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise BadMessage(f"malformed msgpack: {exc}") from None
    if not isinstance(body, dict):
        raise BadMessage("message must be a msgpack map")
    version = body.get("v")
    if version != PROTOCOL_VERSION:
        raise BadMessage(f"unknown protocol version {version!r}; this service speaks {PROTOCOL_VERSION}")
    return body


def _int(body: dict[str, Any], name: str) -> int:
    value = body.get(name)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise BadMessage(f"field {name!r} must be a non-negative integer, got {value!r}")
    return value


def _str(body: dict[str, Any], name: str, default: str | None = None) -> str:
    value = body.get(name, default)
    if not isinstance(value, str):
        raise BadMessage(f"field {name!r} must be a string, got {value!r}")
    return value


def _time(body: dict[str, Any]) -> float:
    """The send time ``t`` (seconds since the epoch); 0.0 when absent."""
    value = body.get("t", 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BadMessage(f"field 't' must be a number, got {value!r}")
    return float(value)


def _float_list(body: dict[str, Any], name: str, size: int | None) -> tuple[float, ...]:
    value = body.get(name)
    if not isinstance(value, (list, tuple)) or (size is not None and len(value) != size):
        want = f"{size} numbers" if size is not None else "a list of numbers"
        raise BadMessage(f"field {name!r} must be {want}, got {value!r}")
    try:
        numbers = tuple(map(float, value))  # map, not a generator: this runs on every latent the learner reads
    except (TypeError, ValueError):
        raise BadMessage(f"field {name!r} holds a non-number") from None
    if not all(map(math.isfinite, numbers)):
        raise BadMessage(f"field {name!r} holds NaN or infinity")
    return numbers


def _optional_prior(body: dict[str, Any], name: str) -> Prior | None:
    """A list of at most :data:`MAX_PRIOR_SIZE` finite numbers, or None when absent."""
    if body.get(name) is None:
        return None
    if not isinstance(body[name], (list, tuple)) or not 0 < len(body[name]) <= MAX_PRIOR_SIZE:
        raise BadMessage(f"field {name!r} must be a list of 1 to {MAX_PRIOR_SIZE} numbers or absent, "
                         f"got {body[name]!r}")  # fmt: skip
    if any(isinstance(value, bool) for value in body[name]):
        raise BadMessage(f"field {name!r} holds a non-number")
    return _float_list(body, name, None)


def _if_set(name: str, value: Prior | None) -> dict[str, list[float]]:
    """``{name: [values]}``, or nothing for None: an unset prior costs no bytes."""
    return {} if value is None else {name: list(value)}


@dataclass(frozen=True)
class ActionMsg:
    """Learner -> sim: apply ``action`` as step ``seq`` of episode ``ep``.

    ``route`` names the encoder that must encode the resulting observation
    (or ``direct``); the learner chooses it so the party that notices a dead
    encoder (by timing out) is the one that re-routes. ``prior`` is the previous
    latent's ``next_prior`` handed back (None at an episode's start or from a
    non-tracking encoder): the sim echoes it to the encoder, which keeps no state.
    """

    ep: int
    seq: int
    action: tuple[float, float, float, float]
    dive_mode: DiveMode = DiveMode.DEPTH_HOLD
    route: str = DIRECT_ROUTE
    sender: str = ""  # the claimant's id; the sim refuses actions from anyone but the holder
    sent_at: float = field(default_factory=time.time)
    prior: Prior | None = None  # the tracking encoder's state after the previous frame

    def fields(self) -> dict[str, Any]:
        return {
            "t": self.sent_at,
            "action": list(self.action),
            "dive_mode": self.dive_mode.value,
            "route": self.route,
            "sender": self.sender,
            **_if_set("prior", self.prior),
        }

    @classmethod
    def from_item(cls, item: BatchItem) -> ActionMsg:
        body = item.body
        action = _float_list(body, "action", ACTION_SIZE)
        if any(abs(a) > 1.0 for a in action):
            raise BadMessage(f"action components must lie in [-1, 1], got {list(action)}")
        try:
            dive_mode = DiveMode(_str(body, "dive_mode", DiveMode.DEPTH_HOLD.value))
        except ValueError:
            raise BadMessage(f"unknown dive_mode {body.get('dive_mode')!r}") from None
        return cls(
            ep=item.ep,
            seq=item.seq,
            action=action,  # type: ignore[arg-type]
            dive_mode=dive_mode,
            route=_str(body, "route", DIRECT_ROUTE),
            sender=_str(body, "sender", ""),
            sent_at=_time(body),
            prior=_optional_prior(body, "prior"),
        )


def image_to_fields(image: np.ndarray) -> dict[str, Any]:
    return {"image": image.tobytes(), "shape": list(image.shape), "dtype": "uint8"}


def image_from_fields(body: dict[str, Any], expected_shape: tuple[int, ...] | None = None) -> np.ndarray:
    """Rebuild an HxWx3 uint8 image, refusing wrong dtype, shape or byte count."""
    if body.get("dtype", "uint8") != "uint8":
        raise BadMessage(f"image dtype must be uint8, got {body.get('dtype')!r}")
    shape = body.get("shape")
    if (
        not isinstance(shape, (list, tuple))
        or len(shape) != 3
        or shape[2] != 3
        or not all(isinstance(s, int) and s > 0 for s in shape)
    ):
        raise BadMessage(f"image shape must be [H, W, 3], got {shape!r}")
    if expected_shape is not None and tuple(shape) != tuple(expected_shape):
        raise BadMessage(f"image shape {list(shape)} differs from the expected {list(expected_shape)}")
    data = body.get("image")
    if not isinstance(data, (bytes, bytearray)) or len(data) != shape[0] * shape[1] * 3:
        raise BadMessage(f"image bytes do not match shape {list(shape)}")
    return np.frombuffer(data, dtype=np.uint8).reshape(shape)


@dataclass(frozen=True)
class ObservationMsg:
    """Sim -> encoder or learner: the world after step ``seq`` of episode ``ep``."""

    env: str
    ep: int
    seq: int
    telemetry: Telemetry
    image: np.ndarray | None  # HxWx3 uint8; None from a sim that does not render (state observations)
    sent_at: float = field(default_factory=time.time)
    prior: Prior | None = None  # the action's prior, echoed for the encoder; None after a reset

    def fields(self) -> dict[str, Any]:
        image = image_to_fields(self.image) if self.image is not None else {}
        return {"t": self.sent_at, "telemetry": self.telemetry.to_dict(), **image, **_if_set("prior", self.prior)}

    @classmethod
    def from_item(cls, item: BatchItem, expected_shape: tuple[int, ...] | None = None) -> ObservationMsg:
        """``expected_shape`` given: the image is required and must have it; otherwise a missing image is None."""
        body = item.body
        if "image" not in body and expected_shape is not None:
            raise BadMessage(f"observation carries no image, expected {list(expected_shape)} (does the sim render?)")
        return cls(
            env=item.env,
            ep=item.ep,
            seq=item.seq,
            telemetry=_telemetry(body),
            image=image_from_fields(body, expected_shape) if "image" in body else None,
            sent_at=_time(body),
            prior=_optional_prior(body, "prior"),
        )


def _telemetry(body: dict[str, Any]) -> Telemetry:
    raw = body.get("telemetry")
    if not isinstance(raw, dict):
        raise BadMessage("field 'telemetry' must be a map")
    try:
        return Telemetry.from_dict(raw)
    except (ValueError, TypeError) as exc:
        raise BadMessage(str(exc)) from None


@dataclass(frozen=True)
class LatentMsg:
    """Encoder -> learner: the latent of one observation, telemetry passed through."""

    env: str
    ep: int
    seq: int
    telemetry: Telemetry
    mu: tuple[float, ...]
    logvar: tuple[float, ...]
    encoder: str
    sent_at: float = field(default_factory=time.time)
    next_prior: Prior | None = None  # a tracking encoder's prior for the env's next frame, for the learner to hand back

    def fields(self) -> dict[str, Any]:
        return {
            "t": self.sent_at,
            "telemetry": self.telemetry.to_dict(),
            "mu": list(self.mu),
            "logvar": list(self.logvar),
            "encoder": self.encoder,
            **_if_set("next_prior", self.next_prior),
        }

    @classmethod
    def from_item(cls, item: BatchItem) -> LatentMsg:
        body = item.body
        mu = _float_list(body, "mu", None)
        return cls(
            env=item.env,
            ep=item.ep,
            seq=item.seq,
            telemetry=_telemetry(body),
            mu=mu,
            logvar=_float_list(body, "logvar", len(mu)),
            encoder=_str(body, "encoder"),
            sent_at=_time(body),
            next_prior=_optional_prior(body, "next_prior"),
        )


StepMsg = ActionMsg | ObservationMsg | LatentMsg


@dataclass(frozen=True)
class BatchItem:
    """One env's part of a :class:`BatchMsg`: its message's fields, or why the sender refused its step."""

    env: str
    ep: int
    seq: int
    body: dict[str, Any] = field(default_factory=dict)  # an ActionMsg's, ObservationMsg's or LatentMsg's fields()
    error: str = ""  # set instead of ``body`` when the sender refused this env's step

    @classmethod
    def of(cls, env: str, message: StepMsg) -> BatchItem:
        return cls(env, message.ep, message.seq, message.fields())


@dataclass(frozen=True)
class BatchMsg:
    """The one message of the step pipeline, each way: a group of envs' actions, observations or latents.

    A learner sends its group's actions in one message (a single env is a group of one); the sim steps them in
    order and answers with one message of their observations; an encoder encodes those in one forward pass and
    answers with one of latents. Each item keeps its env's own (ep, seq), so retries and duplicate dropping work
    per env; ``to`` names the learner an answer is for, so a refusal of somebody else's actions is not taken for
    a refusal of its own. The items' fields travel inside the one map, so a step costs one msgpack pass each way.
    """

    group: str
    sender: str
    items: tuple[BatchItem, ...]
    to: str = ""  # an answer's addressee: the sender of the actions it answers ("" in the actions themselves)
    sent_at: float = field(default_factory=time.time)

    @classmethod
    def alone(cls, item: BatchItem, sender: str = "", to: str = "") -> BatchMsg:
        """One env's item as its own group of one, the group named after the env."""
        return cls(item.env, sender, (item,), to)

    def encode(self) -> bytes:
        items = [[item.env, item.ep, item.seq, item.body, item.error] for item in self.items]
        return _pack(
            {"v": PROTOCOL_VERSION, "t": self.sent_at, "group": self.group, "sender": self.sender, "to": self.to,
             "items": items}
        )  # fmt: skip

    @classmethod
    def decode(cls, payload: bytes) -> BatchMsg:
        body = unpack(payload)
        raw = body.get("items")
        if not isinstance(raw, list) or not raw:
            raise BadMessage("field 'items' must be a non-empty list")
        items = tuple(map(_item, raw, range(len(raw))))
        return cls(_str(body, "group"), _str(body, "sender", ""), items, _str(body, "to", ""), _time(body))


def _item(entry: Any, index: int) -> BatchItem:
    if not isinstance(entry, list) or len(entry) != 5:
        raise BadMessage(f"item {index} must be [env, ep, seq, fields, error], got {entry!r:.80}")
    env, ep, seq, fields_, error = entry
    if not isinstance(env, str) or not isinstance(error, str):
        raise BadMessage(f"item {index}'s env and error must be strings, got {env!r:.40} and {error!r:.80}")
    if type(ep) is not int or type(seq) is not int or ep < 0 or seq < 0:
        raise BadMessage(f"item {index}'s ep and seq must be non-negative integers, got {ep!r} and {seq!r}")
    if not isinstance(fields_, dict):
        raise BadMessage(f"item {index}'s fields must be a map, got {type(fields_).__name__}")
    return BatchItem(env, ep, seq, fields_, error)


def batch_messages(payload: bytes, read: Callable[[BatchItem], M]) -> list[tuple[str, M]]:
    """(env, message) of each item of a step message that carries one (a refused item has none), for readers that
    follow envs rather than groups (recordings, the live view); BadMessage if any of it is unreadable."""
    return [(item.env, read(item)) for item in BatchMsg.decode(payload).items if not item.error]


# --- the control plane: request/reply on ``<ns>/<channel>/<env>/ctl`` (services/control.py) -------------------------
# Same codec and refusal rules as the step messages: a version-checked map, every field checked on decoding. A
# request names its op; a reply carries ``ok``: the request's typed answer, or a Refused with the reason.


def _pack_control(**fields_: Any) -> bytes:
    return _pack({"v": PROTOCOL_VERSION, "t": time.time(), **fields_})


def _optional_str(body: dict[str, Any], name: str) -> str | None:
    return None if body.get(name) is None else _str(body, name)


def _bool(body: dict[str, Any], name: str) -> bool:
    value = body.get(name)
    if not isinstance(value, bool):
        raise BadMessage(f"field {name!r} must be true or false, got {value!r}")
    return value


def _optional_map(body: dict[str, Any], name: str) -> dict | None:
    value = body.get(name)
    if value is None or isinstance(value, dict):
        return value
    raise BadMessage(f"field {name!r} must be a map or absent, got {value!r}")


def _switch_or_map(body: dict[str, Any], name: str) -> bool | dict | None:
    value = body.get(name)
    if value is None or isinstance(value, (bool, dict)):
        return value
    raise BadMessage(f"field {name!r} must be true, false, a map or absent, got {value!r}")


@dataclass(frozen=True)
class EnvState:
    """The answer to a granted claim or release, and the start of every other: where the env is and who holds it."""

    channel: str
    env: str
    holder: str | None  # None: free
    ep: int
    seq: int

    def encode(self) -> bytes:
        return _pack_control(ok=True, **asdict(self))

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> EnvState:
        return cls(**cls._state(body))

    @staticmethod
    def _state(body: dict[str, Any]) -> dict[str, Any]:
        return {
            "channel": _str(body, "channel"),
            "env": _str(body, "env"),
            "holder": _optional_str(body, "holder"),
            "ep": _int(body, "ep"),
            "seq": _int(body, "seq"),
        }


@dataclass(frozen=True)
class InfoReply(EnvState):
    """The answer to ``info``: the env's state, the sim serving it and the size of the images it renders."""

    sim: str
    image_size: int

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> InfoReply:
        return cls(**cls._state(body), sim=_str(body, "sim"), image_size=_int(body, "image_size"))


@dataclass(frozen=True)
class ResetReply(EnvState):
    """The answer to ``reset`` (its observation goes out as a step message); ``replayed``: a repeat, from the cache."""

    replayed: bool

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> ResetReply:
        return cls(**cls._state(body), replayed=_bool(body, "replayed"))


@dataclass(frozen=True)
class Refused:
    """The answer to a control request that was refused, with the reason."""

    reason: str

    def encode(self) -> bytes:
        return _pack_control(ok=False, error=self.reason)


R = TypeVar("R", bound=EnvState)


def decode_reply(payload: bytes, expected: type[R]) -> R | Refused:
    """A reply to a request whose answer is an ``expected``, or its refusal; BadMessage if unreadable."""
    body = unpack(payload)
    return expected.from_body(body) if _bool(body, "ok") else Refused(_str(body, "error"))


class ControlRequest:
    """A control request: its ``OP`` on the wire and the type of its granted reply."""

    OP: ClassVar[str]
    REPLY: ClassVar[type[EnvState]] = EnvState

    def encode(self) -> bytes:
        fields_ = {name: value for name, value in asdict(self).items() if value is not None}  # None: absent
        return _pack_control(op=self.OP, **fields_)


@dataclass(frozen=True)
class InfoRequest(ControlRequest):
    """Who holds the env and where it is, asked of every env by `swimm status` and evaluators looking for one."""

    OP: ClassVar[str] = "info"
    REPLY: ClassVar[type[EnvState]] = InfoReply

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> InfoRequest:
        return cls()


@dataclass(frozen=True)
class HolderRequest(ControlRequest):
    """A request that names only the learner (``holder``) it is made for."""

    holder: str

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> HolderRequest:
        return cls(_str(body, "holder"))


@dataclass(frozen=True)
class ClaimRequest(HolderRequest):
    """Hold the env for ``holder``: nobody else may drive it until released (or the holder's token lapses)."""

    OP: ClassVar[str] = "claim"


@dataclass(frozen=True)
class ReleaseRequest(HolderRequest):
    """Give back an env ``holder`` holds."""

    OP: ClassVar[str] = "release"


@dataclass(frozen=True)
class ResetRequest(ControlRequest):
    """Start episode ``ep`` from world seed ``seed``, its observation to ``route``; ``noise``, ``latency`` and
    ``scene`` (maps of the sim's settings, ``noise`` also on or off) change the world from this episode on, None
    leaving each as it is."""

    OP: ClassVar[str] = "reset"
    REPLY: ClassVar[type[EnvState]] = ResetReply
    holder: str
    ep: int
    seed: int
    route: str = DIRECT_ROUTE
    noise: bool | dict | None = None
    latency: dict | None = None
    scene: dict | None = None

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> ResetRequest:
        return cls(
            holder=_str(body, "holder"),
            ep=_int(body, "ep"),
            seed=_int(body, "seed"),
            route=_str(body, "route", DIRECT_ROUTE),
            noise=_switch_or_map(body, "noise"),
            latency=_optional_map(body, "latency"),
            scene=_optional_map(body, "scene"),
        )


AnyControlRequest = InfoRequest | ClaimRequest | ReleaseRequest | ResetRequest
CONTROL_REQUESTS: dict[str, type[AnyControlRequest]] = {
    request.OP: request for request in (InfoRequest, ClaimRequest, ReleaseRequest, ResetRequest)
}


def decode_request(payload: bytes) -> AnyControlRequest:
    """The control request in ``payload``, of the type its op names; BadMessage naming what is wrong."""
    body = unpack(payload)
    op = _str(body, "op")
    if op not in CONTROL_REQUESTS:
        raise BadMessage(f"unknown control op {op!r} (known: {', '.join(CONTROL_REQUESTS)})")
    return CONTROL_REQUESTS[op].from_body(body)
