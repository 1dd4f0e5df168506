"""Attaching an evaluation learner to a live sim: find the sims' eval envs, pick a free one, claim it.

A sim serves its ``eval`` channel beside ``train``; an evaluator can come and go at any time without the
training learner noticing, because the two channels are separate envs (separate Worlds) of the same process.
Discovery asks every ``<ns>/eval/*/ctl`` for its ``info`` (who holds it), so the error says exactly what
is wrong: no sim at all, or every eval env held (and by whom).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from learner_service.live_encoders import require_live_encoders
from learner_service.proxy_env import ClaimRefused, ProxyEnv, ProxySettings
from learner_service.task import TaskSettings
from services.control import survey
from services.keys import Keys
from services.messages import InfoReply
from services.session import build_config, describe_endpoints, open_session
from services.settings import ZenohSettings

log = logging.getLogger(__name__)

EVAL_CHANNEL = "eval"
SURVEY_POLL_S = 0.5  # between discovery attempts while no sim answers yet


class NoEvalEnv(RuntimeError):
    """No eval env can be claimed: no live sim serves the namespace, or every eval env is held."""


def eval_env_pattern(keys: Keys) -> str:
    return keys.ctl(EVAL_CHANNEL, "*")


def discover_eval_envs(session: Any, keys: Keys, wait_s: float) -> list[InfoReply]:
    """The ``info`` of every eval env that answers, waiting (bounded, logged) until at least one does."""
    deadline = time.monotonic() + wait_s
    logged = False
    while True:
        found = survey(session, eval_env_pattern(keys), timeout_s=2.0)
        if found or time.monotonic() >= deadline:
            return sorted(found, key=lambda info: (info.sim, info.env))
        if not logged:
            log.info("no eval env answers on %s yet; waiting up to %.0f s for a sim", eval_env_pattern(keys), wait_s)
            logged = True
        time.sleep(SURVEY_POLL_S)


def free_env_ids(infos: list[InfoReply], zenoh: ZenohSettings) -> list[str]:
    """Ids of the unheld eval envs, highest first; NoEvalEnv naming the namespace, endpoint or holders when there
    is none."""
    if not infos:
        raise NoEvalEnv(
            f"no live sim serves {zenoh.namespace}/{EVAL_CHANNEL}/*"
            f" (connected to {describe_endpoints(build_config(zenoh))}):"
            f" start `swimm sim --namespace {zenoh.namespace}` or fix --connect/--namespace"
        )
    # highest id first: a training learner's own evaluation callback takes eval/0, so leave it the low ids
    free = sorted((info.env for info in infos if not info.holder), key=_id_order, reverse=True)
    if not free:
        held = ", ".join(f"{EVAL_CHANNEL}/{info.env} by {info.holder}" for info in infos)
        raise NoEvalEnv(f"every eval env is held ({held}); wait for one, or start the sim with more --eval-envs")
    return free


def _id_order(env_id: str) -> tuple[int, int, str]:
    """Numeric ids in numeric order (10 after 9), after any others."""
    return (1, int(env_id), "") if env_id.isdigit() else (0, 0, env_id)


@contextmanager
def attached_eval_env(
    task: TaskSettings,
    zenoh: ZenohSettings,
    base_seed: int,
    wait_s: float = 10.0,
    step_timeout_s: float = 2.0,
    max_retries: int = 10,
    encoder: str | None = None,
) -> Iterator[ProxyEnv]:
    """A claimed eval env of a live sim as a ProxyEnv; released (and its session closed) on exit.

    Envs that another evaluator claims between the survey and our claim are skipped for the next free one. With
    ``encoder`` (the CMVAE the policies read), every live encoder must run it.
    """
    keys = Keys(zenoh.namespace)
    with open_session(zenoh, role="eval") as session:
        if encoder is not None:
            require_live_encoders(session, keys, encoder, f"this evaluation (encoder {encoder})", wait_s)
        candidates = free_env_ids(discover_eval_envs(session, keys, wait_s), zenoh)
        proxy = ProxySettings(zenoh, channel=EVAL_CHANNEL, envs=tuple(candidates), step_timeout_s=step_timeout_s,
                              max_retries=max_retries, role="eval")  # fmt: skip
        env, refusals = None, []
        for env_id in candidates:
            try:
                env = ProxyEnv(task, proxy, env_id, base_seed, session=session)
                break
            except ClaimRefused as exc:
                refusals.append(str(exc))
        if env is None:
            raise NoEvalEnv("every free eval env was claimed by someone else first: " + "; ".join(refusals))
        log.info("attached to %s/%s (holder %s)", zenoh.namespace, env.name, env.holder)
        with env:
            yield env
