"""An exponential moving average of the acting network's weights: what the run evaluates and delivers.

SAC from scratch here reaches a good policy and then wanders off it: every run of the 8-minute benchmark ended
10 to 26% below its best evaluation (docs/learner.md). Averaging the weights of the last few thousand updates
(Polyak averaging, as the target networks already do for the critic) irons out the late updates' swings without
slowing the learning itself, since the learner keeps training its own, live weights.

A hook on the acting network's optimizer (the actor of an off-policy learner, the whole policy otherwise) folds
the weights into the average after every step, so the learner's ``train`` is untouched (as in smoothness.py).
:meth:`ActorAverage.swapped_in` puts the average in place for as long as an evaluation or a save lasts.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

#: The average's decay ramps up as (1 + n) / (WARMUP + n) over its first updates, so that it does not start out
#: weighted towards the untrained weights (the num_updates rule of TensorFlow's ExponentialMovingAverage).
WARMUP = 10


class ActorAverage:
    """The running average over about ``updates`` optimizer steps of ``model``'s acting network."""

    def __init__(self, model: Any, updates: int) -> None:
        if updates < 1:
            raise ValueError(f"--actor-average counts optimizer updates and must be >= 1, got {updates}")
        self.network: torch.nn.Module = model.actor if hasattr(model, "actor") else model.policy
        if not isinstance(getattr(self.network, "optimizer", None), torch.optim.Optimizer):
            raise ValueError(f"--actor-average needs the acting network's own optimizer; {type(model).__name__} "
                             "has none on its actor or policy")  # fmt: skip
        self.decay = 1.0 - 1.0 / updates
        self.updates = 0
        self.average = [parameter.detach().clone() for parameter in self.network.parameters()]
        self.network.optimizer.register_step_post_hook(lambda *_: self.fold_in())

    @torch.no_grad()
    def fold_in(self) -> None:
        """Move the average towards the network's current weights (after each optimizer step)."""
        self.updates += 1
        weight = 1.0 - min(self.decay, (1 + self.updates) / (WARMUP + self.updates))
        for average, parameter in zip(self.average, self.network.parameters(), strict=True):
            average.lerp_(parameter.detach(), weight)

    @contextmanager
    def swapped_in(self) -> Iterator[None]:
        """The averaged weights in the network while the block runs; the live ones back afterwards."""
        live = [parameter.detach().clone() for parameter in self.network.parameters()]
        self._load(self.average)
        try:
            yield
        finally:
            self._load(live)

    @torch.no_grad()
    def _load(self, weights: list[torch.Tensor]) -> None:
        for parameter, value in zip(self.network.parameters(), weights, strict=True):
            parameter.copy_(value)
