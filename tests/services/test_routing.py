"""Which encoder a frame or a group goes to: rendezvous hashing, and its bounded-load form over a learner's groups."""

from __future__ import annotations

import itertools
import math

import pytest

from services.presence import balanced_choice, rendezvous_choice

ENCODERS = {f"encoder-{i}" for i in range(4)}


def groups(count: int, learner: str = "learner-ab12") -> list[str]:
    return [f"train/groups/{learner}.{i}" for i in range(count)]


@pytest.mark.parametrize(("group_count", "encoder_count"), [(2, 2), (3, 2), (4, 4), (8, 3), (5, 4)])
def test_groups_spread_evenly_over_the_encoders(group_count, encoder_count):
    members = set(sorted(ENCODERS)[:encoder_count])
    siblings = groups(group_count)
    chosen = [balanced_choice(group, siblings, members) for group in siblings]
    loads = [chosen.count(member) for member in members]
    assert max(loads) <= math.ceil(group_count / encoder_count)
    assert max(loads) - min(loads) <= 1  # nobody idles while another holds two more
    assert set(chosen) <= members


def test_plain_rendezvous_can_stack_two_groups_on_one_of_two_encoders():
    """Why the balanced form exists: some learners' two groups hash to one encoder."""
    members = {"encoder-0", "encoder-1"}
    stacked = [
        learner
        for learner in (f"learner-{i}" for i in range(40))
        if len({rendezvous_choice(group, members) for group in groups(2, learner)}) == 1
    ]
    assert stacked, "expected some of 40 learners' groups to collide under plain rendezvous hashing"
    for learner in stacked:
        siblings = groups(2, learner)
        assert {balanced_choice(group, siblings, members) for group in siblings} == members


def test_the_choice_does_not_depend_on_the_order_siblings_are_listed_in():
    siblings = groups(5)
    for order in itertools.islice(itertools.permutations(siblings), 20):
        assert [balanced_choice(g, list(order), ENCODERS) for g in siblings] == [
            balanced_choice(g, siblings, ENCODERS) for g in siblings
        ]


def test_one_group_goes_where_plain_rendezvous_sends_it():
    (group,) = groups(1)
    assert balanced_choice(group, [group], ENCODERS) == rendezvous_choice(group, ENCODERS)


def test_when_an_encoder_leaves_its_groups_move_to_the_live_ones():
    siblings = groups(4)
    before = {g: balanced_choice(g, siblings, ENCODERS) for g in siblings}
    gone = before[siblings[0]]
    live = ENCODERS - {gone}
    after = {g: balanced_choice(g, siblings, live) for g in siblings}
    assert gone not in after.values()
    assert max(list(after.values()).count(m) for m in live) <= math.ceil(len(siblings) / len(live))


def test_a_key_outside_its_siblings_is_refused():
    with pytest.raises(ValueError, match="not among its siblings"):
        balanced_choice("train/groups/x.9", groups(2), ENCODERS)
