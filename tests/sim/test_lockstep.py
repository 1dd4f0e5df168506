"""sim_service/lockstep.py, the lock-step contract without Zenoh: who may drive an env, and which (episode, seq)
steps the world, is answered from the cache, or is refused."""

from __future__ import annotations

import pytest

from services.messages import ActionMsg, BatchItem, ObservationMsg
from sim_service.lockstep import LockstepEnv, Refusal
from sim_service.settings import WorldSettings
from sim_service.world import World

HOLDER, OTHER = "learner-a", "learner-b"
SURGE = (0.0, 0.0, 0.6, 0.1)


@pytest.fixture
def env():
    world = World(WorldSettings(render=False))  # telemetry alone tells whether the world stepped
    yield LockstepEnv("train", "0", world)
    world.close()


def action(
    seq: int, ep: int = 1, sender: str = HOLDER, values=SURGE, prior: tuple[float, ...] | None = None
) -> ActionMsg:
    return ActionMsg(ep=ep, seq=seq, action=values, sender=sender, prior=prior)


def observed(item: BatchItem) -> ObservationMsg:
    return ObservationMsg.from_item(item)


def started(env: LockstepEnv, ep: int = 1, seed: int = 7) -> ObservationMsg:
    env.claim(HOLDER)
    return observed(env.reset(HOLDER, ep, seed).item)


def test_only_the_holder_drives_and_a_second_claimant_hears_who_holds_it(env):
    with pytest.raises(Refusal, match="not claimed"):
        env.reset(HOLDER, 1, 7)
    env.claim(HOLDER)
    env.claim(HOLDER)  # claiming again is harmless
    with pytest.raises(Refusal, match=f"held by {HOLDER}"):
        env.claim(OTHER)
    env.reset(HOLDER, 1, 7)
    with pytest.raises(Refusal, match=f"held by {HOLDER}, not {OTHER}"):
        env.act(action(1, sender=OTHER))
    with pytest.raises(Refusal, match=f"not held by {OTHER}"):
        env.release(OTHER)
    env.release(HOLDER)
    env.claim(OTHER)
    assert env.holder == OTHER


def test_a_lapsed_claim_frees_the_env_only_for_a_gone_holder(env):
    env.claim(HOLDER)
    env.lapse({OTHER})
    assert env.holder == HOLDER
    env.lapse({HOLDER, OTHER})
    assert env.holder is None
    env.claim(OTHER)


def test_the_next_seq_steps_once_and_a_repeat_is_answered_from_the_cache(env):
    reset = started(env)
    first = env.act(action(1))
    assert not first.replayed and observed(first.item).seq == 1
    assert observed(first.item).telemetry.sim_time == pytest.approx(reset.telemetry.sim_time + env.world.dt)
    again = env.act(action(1, values=(0.0, 0.0, -1.0, 0.0)))  # a retry: its action is not applied
    assert again.replayed and again.item == first.item
    second = observed(env.act(action(2)).item)
    assert second.seq == 2
    assert second.telemetry.sim_time == pytest.approx(reset.telemetry.sim_time + 2 * env.world.dt)


def test_the_same_actions_give_the_same_steps_with_or_without_retries(env):
    started(env)
    with_retries = []
    for seq in range(1, 6):
        env.act(action(seq))
        with_retries.append(observed(env.act(action(seq)).item).telemetry)  # every step sent twice
    fresh = LockstepEnv("train", "1", World(WorldSettings(render=False)))
    try:
        started(fresh)
        assert [observed(fresh.act(action(seq)).item).telemetry for seq in range(1, 6)] == with_retries
    finally:
        fresh.world.close()


def test_each_observation_carries_its_actions_prior_a_retrys_own_and_a_resets_none(env):
    assert started(env).prior is None
    assert observed(env.act(action(1, prior=(12.5, 4.0))).item).prior == (12.5, 4.0)
    # A retry after a failover goes to another encoder, which reads the prior the retry carries.
    retry = env.act(action(1, prior=(-3.0,)))
    assert retry.replayed and observed(retry.item).prior == (-3.0,)
    assert observed(env.act(action(2)).item).prior is None  # an encoder that does not track sends none back
    assert observed(env.reset(HOLDER, 2, 7).item).prior is None
    assert observed(env.reset(HOLDER, 2, 7).item).prior is None  # the repeated reset's replay too


@pytest.mark.parametrize("seq", [0, 3], ids=["behind", "ahead"])
def test_an_out_of_order_seq_is_refused_naming_the_expected_one(env, seq):
    started(env)
    env.act(action(1))
    with pytest.raises(Refusal, match="expected 2"):
        env.act(action(seq))


def test_episodes_only_move_forward_and_a_repeated_reset_replays(env):
    with pytest.raises(Refusal, match="not claimed"):
        env.act(action(1))
    first = started(env, ep=2, seed=11)
    replay = env.reset(HOLDER, 2, 11)
    assert replay.replayed and observed(replay.item) == first
    with pytest.raises(Refusal, match="episode 1 is not after the current episode 2"):
        env.reset(HOLDER, 1, 11)
    with pytest.raises(Refusal, match="action for episode 1, but the current episode is 2"):
        env.act(action(1, ep=1))
    assert observed(env.reset(HOLDER, 3, 11).item).ep == 3
