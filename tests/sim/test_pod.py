"""Pods: companions swim beside the target, replay from the seed, show in the frame and cross its line of sight."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from services.geometry import ALPHA_DEG
from services.identity import NONE, TARGET, off_axis_deg, target_occluded
from services.settings import load
from services.telemetry import Telemetry
from sim_service.pod import PodParams
from sim_service.scenery_model import part_names
from sim_service.settings import MAX_POD_SIZE, DolphinSettings, WorldSettings, world_of_file
from sim_service.world import CAMERA, TARGET_BOX, World


def pod_world(size: int, render: bool = True, motion: str = "planar", crossing: bool = False) -> World:
    dolphin = DolphinSettings(motion=motion, pod_size=size, pod_crossing=crossing)
    return World(WorldSettings(render=render, dolphin=dolphin))


def target_only(telemetry: Telemetry) -> Telemetry:
    """``telemetry`` with the pod's identity fields at a lone dolphin's values: what the pod leaves as it was."""
    return dataclasses.replace(telemetry, pod_size=1, followed=0, target_occluded=False)


def dolphins_in_camera(world: World) -> np.ndarray:
    """Every dolphin's body centre, the target first, in the camera's (forward, left, up) frame."""
    bodies = [world.model.body(part_names(index)[0]).id for index in range(world.pod.size)]
    return world._in_camera(world.data.xpos[bodies])


def companion_positions(world: World) -> np.ndarray:
    """Each companion's body position, (companions, 3), as MuJoCo holds it."""
    bodies = [world.model.body(part_names(index)[0]).id for index in range(1, world.pod.size)]
    return world.data.xpos[bodies].copy()


def test_a_pod_replays_from_its_seed_and_leaves_the_targets_swim_as_it_was():
    first, second, single = pod_world(4), pod_world(4), pod_world(1, render=False)
    actions = np.random.default_rng(11).uniform(-1, 1, size=(150, 4))
    telemetry, frame = first.reset(11)
    again, frame_again = second.reset(11)
    assert telemetry == again and np.array_equal(frame, frame_again)
    assert target_only(telemetry) == target_only(single.reset(11)[0])
    for action in actions:
        second.prepare_step()  # preparing ahead, as a lock-step server does, changes nothing either
        (telemetry, frame), (again, frame_again) = first.step(tuple(action)), second.step(tuple(action))
        assert telemetry == again and np.array_equal(frame, frame_again)
        assert target_only(telemetry) == target_only(single.step(tuple(action))[0])
        assert np.array_equal(companion_positions(first), companion_positions(second))
    for world in (first, second, single):
        world.close()


def test_companions_are_drawn_in_the_frame():
    world, single = pod_world(4), pod_world(1)
    camera = world.model.camera(CAMERA).id
    seen = 0
    for seed in range(3):
        _, frame = world.reset(seed)
        assert not np.array_equal(frame, single.reset(seed)[1])
        for _ in range(100):
            world.step((0, 0, 0, 0))
            for index in range(1, world.pod.size):
                body = world.model.body(part_names(index)[0]).id
                seen += world.frustum.sees_box(
                    world.data.cam_xpos[camera], world.data.cam_xmat[camera].reshape(3, 3), world.data.xpos[body],
                    world.data.xmat[body].reshape(3, 3), TARGET_BOX,
                )  # fmt: skip
    assert seen > 0
    world.close()
    single.close()


def test_companions_cross_the_targets_line_of_sight_some_between_it_and_the_rover():
    world = pod_world(4, render=False)
    crossings = in_front = 0
    for seed in range(3):
        world.reset(seed)
        sides = []
        for _ in range(3000):
            telemetry, _ = world.step((0, 0, 0, 0))
            rover, target = np.array(telemetry.rover_pos[:2]), np.array(telemetry.target_pos[:2])
            sight = target - rover
            companions = companion_positions(world)[:, :2] - rover
            sides.append(np.sign(sight[0] * companions[:, 1] - sight[1] * companions[:, 0]))
            nearer = np.linalg.norm(companions, axis=1) < np.linalg.norm(sight)
            if len(sides) > 1:
                flips = sides[-1] != sides[-2]
                crossings += int(flips.sum())
                in_front += int((flips & nearer).sum())
    world.close()
    assert crossings > 0 and in_front > 0


def test_companions_keep_near_the_target_and_to_its_depth_in_the_3d_motion():
    world = pod_world(MAX_POD_SIZE, render=False, motion="3d")
    params = PodParams()
    farthest = math.hypot(max(map(abs, params.along_m)), max(map(abs, params.left_m)))
    world.reset(5)
    for _ in range(3000):
        target = np.array(world.step((0, 0, 0, 0))[0].target_pos)
        offsets = companion_positions(world) - target
        assert np.all(np.linalg.norm(offsets[:, :2], axis=1) <= farthest + 1e-6)
        assert np.all(np.abs(offsets[:, 2]) <= max(map(abs, params.up_m)) + 1e-6)
    world.close()


def test_pod_size_is_a_setting_refused_outside_its_range():
    assert load(WorldSettings).dolphin.pod_size == 1
    assert load(WorldSettings, environ={"SWIMM_DOLPHIN_POD_SIZE": "4"}).dolphin.pod_size == 4
    for size in (0, MAX_POD_SIZE + 1):
        with pytest.raises(ValueError, match=f"--dolphin-pod-size must be 1 to {MAX_POD_SIZE}, got {size}"):
            pod_world(size, render=False)


def test_the_target_is_the_dolphin_the_first_frame_is_centred_on():
    world, margin = pod_world(MAX_POD_SIZE, render=False), PodParams().centred_margin_deg
    for seed in range(20):
        telemetry, _ = world.reset(seed)
        points = dolphins_in_camera(world)
        angles = off_axis_deg(points)
        # The reset's azimuth is the rover centre's: the camera ahead of it may see the target's centre just off the
        # image's edge, and then no dolphin at all is followed.
        assert telemetry.followed == TARGET or (telemetry.followed == NONE and angles[TARGET] > ALPHA_DEG)
        assert not telemetry.target_occluded
        assert np.all(angles[1:] >= angles[TARGET] + margin), (seed, angles)
    world.close()


def test_a_lone_dolphin_is_followed_while_in_view_and_never_occluded():
    world = pod_world(1, render=False)
    world.reset(3)
    followed = set()
    for _ in range(1000):  # the rover holds still: the dolphin swims out of view
        telemetry, _ = world.step((0, 0, 0, 0))
        assert telemetry.pod_size == 1 and not telemetry.target_occluded
        assert telemetry.target_in_frustum or telemetry.followed == NONE
        followed.add(telemetry.followed)
    assert followed == {TARGET, NONE}
    world.close()


def crossing_steps(world: World, seed: int, steps: int) -> list[int]:
    """The steps of an episode of ``seed`` (the rover holding still) at which a companion hides the target."""
    world.reset(seed)
    occluded = []
    for step in range(1, steps + 1):
        telemetry, _ = world.step((0, 0, 0, 0))
        assert telemetry.target_occluded == target_occluded(dolphins_in_camera(world))
        if telemetry.target_occluded:
            occluded.append(step)
    return occluded


def test_the_crossing_split_puts_a_companion_between_the_rover_and_the_target_on_time():
    crossing, single = pod_world(4, crossing=True), pod_world(1)
    params = PodParams()
    first_crossing = round(params.crossing_period_s / 4 / crossing.dt)  # the sway's first zero
    for seed in range(3):
        occluded = crossing_steps(crossing, seed, first_crossing + 20)
        assert first_crossing in occluded, (seed, occluded)
        assert crossing_steps(single, seed, first_crossing + 20) == []
    crossing.close()
    single.close()


def test_the_crossing_companion_hides_target_pixels_in_the_rendered_frame():
    crossing, single = pod_world(4, crossing=True), pod_world(1)
    first_crossing = round(PodParams().crossing_period_s / 4 / crossing.dt)
    for world in (crossing, single):
        world.reset(1)
        for _ in range(first_crossing):
            telemetry, _ = world.step((0, 0, 0, 0))
    # The target's swim and the rover are the same in both worlds: only the companion in front can take its pixels.
    assert telemetry.target_in_frustum and single.target_mask().sum() > 0
    assert crossing.target_mask().sum() < single.target_mask().sum()
    crossing.close()
    single.close()


def test_a_crossing_pod_replays_from_its_seed():
    first, second = pod_world(4, crossing=True), pod_world(4, crossing=True)
    for world in (first, second):
        world.reset(7)
    for _ in range(300):
        second.prepare_step()  # the crossing follows the rover's place before the action, prepared or not
        (telemetry, frame), (again, frame_again) = first.step((0.1, 0, 0.3, 0.2)), second.step((0.1, 0, 0.3, 0.2))
        assert telemetry == again and np.array_equal(frame, frame_again)
    first.close()
    second.close()


def test_crossing_needs_a_companion_and_says_so():
    with pytest.raises(ValueError, match="--dolphin-pod-crossing needs a companion to cross: --dolphin-pod-size 1"):
        pod_world(1, render=False, crossing=True)


def test_the_shipped_pod_configs_describe_a_pod_of_4_and_its_crossing_split():
    configs = Path(__file__).resolve().parents[2] / "sim_service" / "configs"
    plain, crossing = (world_of_file(configs / name).dolphin for name in ("pod4.yaml", "pod4_crossing.yaml"))
    assert (plain.pod_size, plain.pod_crossing) == (4, False)
    assert (crossing.pod_size, crossing.pod_crossing) == (4, True)
