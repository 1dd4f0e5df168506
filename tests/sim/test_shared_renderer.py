"""Worlds sharing one renderer (one GL context per sim process) draw exactly the frames of worlds with their own.

A sim steps its envs' Worlds one after another on one thread, so they can share a renderer; each draws its own model
and data into it. What could differ is whatever the GL context took from the first world's model, or what one
world's frame leaves behind for the next: so the worlds here differ per episode in scenery, the pod's looks and
image noise (fog and depth of field read a depth render), they are stepped interleaved, and segmentation masks are
rendered between frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_service.scenery import SceneSettings
from sim_service.settings import DolphinSettings, WorldSettings
from sim_service.world import World

WORLDS = 3
STEPS = 60
SETTINGS = WorldSettings(scene=SceneSettings(preset="varied"), dolphin=DolphinSettings(pod_size=3))


def worlds(shared: bool) -> list[World]:
    built: list[World] = []
    for _ in range(WORLDS):
        built.append(World(SETTINGS, share_renderer_with=built[0] if shared and built else None))
    return built


def play(group: list[World]) -> list[np.ndarray]:
    """Frames and masks of interleaved episodes: world i on seed i, its odd episodes noisy, actions from one seed."""
    rng = np.random.default_rng(7)
    seen = []
    for episode in range(2):
        seen += [world.reset(10 * episode + i, noise=episode % 2 == 1)[1] for i, world in enumerate(group)]
        for step in range(STEPS):
            for world in group:
                seen.append(world.step(tuple(rng.uniform(-1, 1, 4)))[1])
                if step % 20 == 0:
                    seen += world.dolphin_masks()
    return seen


def test_worlds_sharing_a_renderer_draw_the_frames_and_masks_of_worlds_with_their_own():
    own, shared = worlds(shared=False), worlds(shared=True)
    try:
        expected, got = play(own), play(shared)
    finally:
        for world in own + shared:
            world.close()
    assert len(got) == len(expected)
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))
    frames = [frame for frame in expected if frame.dtype == np.uint8]
    assert len({frame.tobytes() for frame in frames}) > len(frames) // 2  # the worlds do show different scenes


@pytest.mark.parametrize(
    ("other", "named"),
    [(WorldSettings(image_size=32), "image_size"), (WorldSettings(render=False), "renders nothing")],
)
def test_a_world_that_draws_other_frames_cannot_share_its_renderer(other, named):
    source = World(other)
    try:
        with pytest.raises(ValueError, match=named):
            World(WorldSettings(), share_renderer_with=source)
    finally:
        source.close()


def test_closing_one_world_of_a_sharing_group_closes_the_renderer_for_all():
    first = World()
    second = World(share_renderer_with=first)
    second.reset(1)
    first.close()
    with pytest.raises(RuntimeError, match="close"):
        second.step((0.0, 0.0, 0.5, 0.0))
    second.close()  # a second close of the same renderer does nothing
