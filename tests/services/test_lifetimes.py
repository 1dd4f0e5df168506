"""Lifetimes: leaving an owner's ``with`` block closes what it opened and declared, and nothing it was lent."""

from __future__ import annotations

from learner_service.proxy_env import ProxyEnv, ProxySettings
from learner_service.task import TaskSettings
from services.keys import Keys
from services.presence import live_now
from sim_service.responder import SimResponder
from sim_service.settings import SimSettings, WorldSettings
from tests.services.test_control_presence import wait_until


def test_with_blocks_close_what_their_owner_opened_and_leave_what_it_was_lent(
    zenoh_router, zenoh_settings, zenoh_session
) -> None:
    settings = zenoh_settings(zenoh_router)
    keys = Keys(settings.namespace)
    lent = zenoh_session(zenoh_router)
    sim_settings = SimSettings(zenoh=settings, world=WorldSettings(render=False), train_envs=1, eval_envs=0)
    with SimResponder(sim_settings) as sim:
        # its queryable answers (an empty query: refused) once the router has seen it declared
        wait_until(lambda: bool(list(lent.get(keys.ctl("train", "0"), timeout=1.0))))
        with ProxyEnv(TaskSettings(obs="state"), ProxySettings(zenoh=settings)) as env:
            env.reset(seed=1)
            own = env.session
        assert own.is_closed()
        with ProxyEnv(TaskSettings(obs="state"), ProxySettings(zenoh=settings), session=lent) as env:
            env.reset(seed=1)  # the env was released when the first one's block ended
        assert not lent.is_closed()
    assert sim.session.is_closed()
    sim.close()  # a second close does nothing
    env.close()
    assert not list(lent.get(keys.ctl("train", "0"), timeout=1.0))  # no queryable is left to answer
    assert not live_now(lent, keys, "sim")
