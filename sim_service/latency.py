"""The delays of a real camera-to-thruster loop, in physics steps: what the policy sees is late, what it commands
is late, and it may command less often than the physics steps.

A real BlueROV2 loop adds 100 to 200 ms between a frame's exposure and the thrusters' response (video encoding,
the network, inference, MAVLink), and a policy served remotely may run below the sim's 50 Hz. The world models
each part at the step level, so lock-step runs stay reproducible:

* ``observation_delay`` k: the frame an answer carries was rendered k steps earlier (the first frame of an
  episode stands in for the ones before it); telemetry, the ground truth the reward reads, stays current;
* ``action_delay`` m: an action reaches the thrusters m steps after it arrives (neutral before the first);
* ``control_period`` n: a new action is taken every n-th step and held in between (50 Hz / n).

``randomise`` draws each episode's delays from 0 to their setting and its period from 1 to its setting, from the
episode's seed: a training aid, like randomised image noise; evaluation uses fixed settings.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from services.settings import from_message

NEUTRAL = (0.0, 0.0, 0.0, 0.0)


@dataclass
class LatencySettings:
    observation_delay: int = 0  # steps from a frame's render to the answer carrying it (20 ms each at 50 Hz)
    action_delay: int = 0  # steps from an action's arrival to the thrusters applying it
    control_period: int = 1  # steps an action is held: the policy acts every n-th step (50 Hz / n)
    randomise: bool = False  # each episode draws the delays from 0 and the period from 1 up to these settings

    def check(self) -> None:
        if self.observation_delay < 0 or self.action_delay < 0 or self.control_period < 1:
            raise ValueError(
                "latency: observation_delay and action_delay must be >= 0 steps and control_period >= 1, got "
                f"{self.observation_delay}, {self.action_delay} and {self.control_period}"
            )

    @classmethod
    def from_mapping(cls, values: dict) -> LatencySettings:
        """Settings from a reset's ``latency`` map, refusing unknown keys and wrong types by name."""
        settings = from_message(cls, values, "latency")
        settings.check()
        return settings

    @property
    def enabled(self) -> bool:
        return self.observation_delay > 0 or self.action_delay > 0 or self.control_period > 1

    def draw(self, rng: np.random.Generator) -> LatencySettings:
        """One episode's fixed settings (``randomise``: each uniform up to its setting; else these)."""
        if not self.randomise:
            return self
        return replace(
            self,
            observation_delay=int(rng.integers(0, self.observation_delay + 1)),
            action_delay=int(rng.integers(0, self.action_delay + 1)),
            control_period=int(rng.integers(1, self.control_period + 1)),
            randomise=False,
        )


class LatencyLine:
    """One episode's delay line: actions in, the action the thrusters apply out; frames in, the frame seen out."""

    def __init__(self, settings: LatencySettings, first_frame: np.ndarray | None) -> None:
        settings.check()
        self.settings = settings
        self._frames: deque[np.ndarray | None] = deque([first_frame] * settings.observation_delay)
        self._actions: deque[tuple[float, ...]] = deque([NEUTRAL] * settings.action_delay)
        self._held = NEUTRAL
        self._steps = 0

    def action(self, commanded: tuple[float, ...]) -> tuple[float, ...]:
        """The action applied at this step, given the one that arrived with it."""
        if self._steps % self.settings.control_period == 0:
            self._held = tuple(commanded)
        self._steps += 1
        self._actions.append(self._held)
        return self._actions.popleft()

    def frame(self, rendered: np.ndarray | None) -> np.ndarray | None:
        """The frame answered at this step, given the one just rendered."""
        self._frames.append(rendered)
        return self._frames.popleft()


def describe_latency(settings: LatencySettings) -> str:
    """One line for logs: what the loop's delays are."""
    if not settings.enabled:
        return "none"
    text = (f"frames {settings.observation_delay} steps late, actions {settings.action_delay} steps late, "
            f"one action per {settings.control_period} steps")  # fmt: skip
    return f"randomised up to ({text})" if settings.randomise else text


def latency_option(value: object) -> LatencySettings | None:
    """A reset's ``latency`` option: settings from a map, or None (the world's as they are)."""
    if value is None or isinstance(value, LatencySettings):
        return value
    if isinstance(value, dict):
        return LatencySettings.from_mapping(value)
    raise ValueError(f"'latency' must be a map of latency settings or absent, got {value!r}")
