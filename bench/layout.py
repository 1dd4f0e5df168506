"""How a benchmark of several envs lays them out: how many sims, and how many envs to a message."""

from __future__ import annotations

from learner_service.up import group_size_for, largest_whole_group, sim_shares
from services.low_latency import check_low_latency_group
from sim_service.settings import WorldSettings


def default_layout(envs: int, sims: int = 0, group_size: int = -1, low_latency: bool = False) -> tuple[int, int]:
    """(sims, group size) for ``envs`` envs, each as given or, from 4 envs on (an even number), two sims, one per
    core, each stepping one group of half the envs (``low_latency``: the largest whole part of that half whose
    observations fit one message); fewer envs: one sim, each env its own messages."""
    if sims == 0:
        sims = 2 if envs >= 4 and envs % 2 == 0 else 1
    share = sim_shares(envs, sims)[0][1]
    largest_group = share
    if low_latency:  # the benchmarks' sims render the default image size
        largest_group = check_low_latency_group(max(group_size, 0), WorldSettings().image_size)
    if group_size < 0:
        group_size = largest_whole_group(share, largest_group) if envs >= 4 else 0
    return sims, group_size_for(envs, group_size, sims)
