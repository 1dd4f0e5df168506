"""The varied world: plain stays the paper's world pixel for pixel, varied scenery changes frames and never poses,
a seed fixes the scenery, bad settings are refused by name, the fish touch nothing, a live sim takes a reset's
``scene`` map. Real MuJoCo rendering throughout."""

from __future__ import annotations

import queue

import mujoco
import numpy as np
import pytest

from services import control
from services.keys import Keys
from services.messages import ClaimRequest, ObservationMsg, ResetRequest, batch_messages
from services.presence import Roster, announce
from services.session import open_session
from services.settings import ZenohSettings
from sim_service.dataset import write_dataset
from sim_service.scenery import PRESETS, SceneSettings, draw_episode_scene, scene_option
from sim_service.settings import WorldSettings
from sim_service.world import CAMERA, MODEL_PATH, World

VARIED = SceneSettings(preset="varied")


@pytest.fixture(scope="module")
def world():
    world = World()
    yield world
    world.close()


def actions(steps: int, seed: int = 0) -> list[tuple[float, ...]]:
    rng = np.random.default_rng(seed)
    return [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (steps, 4))]


def episode(world: World, seed: int, scene: SceneSettings | None = None, steps: int = 10):
    telemetry, frame = world.reset(seed, scene=scene)
    poses, frames = [telemetry], [frame]
    for action in actions(steps, seed):
        telemetry, frame = world.step(action)
        poses.append(telemetry)
        frames.append(frame)
    return poses, np.stack(frames)


def world_xml_frame(world: World) -> np.ndarray:
    """The current state drawn by a model loaded straight from world.xml, as the world rendered before scenery."""
    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    data = mujoco.MjData(model)
    data.qpos[:] = world.data.qpos
    data.mocap_pos[:] = world.data.mocap_pos[: model.nmocap]
    data.mocap_quat[:] = world.data.mocap_quat[: model.nmocap]
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, 64, 64) as renderer:
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_FOG] = True
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = True
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        renderer.update_scene(data, camera=CAMERA)
        return renderer.render()


def test_the_default_world_draws_world_xml_bit_for_bit_even_after_a_varied_episode(world):
    _, plain = episode(world, 5, steps=3)
    assert np.array_equal(plain[-1], world_xml_frame(world))
    episode(world, 5, VARIED, steps=3)
    _, again = episode(world, 5, SceneSettings(preset="plain"), steps=3)
    assert np.array_equal(again, plain)  # everything a varied episode changed was put back
    assert np.array_equal(again[-1], world_xml_frame(world))


def test_varied_scenery_changes_frames_and_never_the_poses(world):
    plain_poses, plain = episode(world, 8, SceneSettings())
    varied_poses, varied = episode(world, 8, VARIED)
    assert varied_poses == plain_poses  # the scenery draws from its own stream
    assert not np.array_equal(varied, plain)
    assert all(not np.array_equal(a, b) for a, b in zip(varied, plain, strict=True))


def test_a_seed_fixes_the_scenery_and_another_seed_draws_another(world):
    _, first = episode(world, 12, VARIED)
    _, again = episode(world, 12, VARIED)
    _, other = episode(world, 13, VARIED)
    assert np.array_equal(first, again)
    assert first.shape == other.shape and not np.array_equal(first, other)


def test_leaving_out_what_lies_behind_the_rover_changes_no_pixel(world):
    crowded = SceneSettings(preset="varied", rocks=[12, 12], seagrass=[24, 24], particles=[60, 60], light_shafts=[6, 6])
    left_out = 0
    for seed in range(4):
        world.reset(seed, scene=crowded)
        for action in actions(40, seed):
            _, frame = world.step(action)
            movers = world.scenery._movers.geoms
            left_out += int((world.model.geom_group[movers] != 4).sum())
            world.model.geom_group[movers] = 4  # draw them all: the next step leaves them out again
            assert np.array_equal(world._render(), frame)
    assert left_out > 0
    world.reset(0, scene=SceneSettings())


def test_draws_stay_in_their_ranges_and_one_element_never_moves_another():
    ranges = PRESETS["varied"]
    for seed in range(30):
        scene = draw_episode_scene(VARIED, np.random.default_rng(seed))
        assert ranges.rocks[0] <= len(scene.rocks) <= ranges.rocks[1]
        assert ranges.particles[0] <= len(scene.particles) <= ranges.particles[1]
        assert len(scene.shoals) <= ranges.fish_shoals[1]
        assert all(ranges.fish_per_shoal[0] <= fish <= ranges.fish_per_shoal[1] for fish in scene.shoals[:, 5])
        assert ranges.dolphin_scale[0] <= scene.dolphin_scale <= ranges.dolphin_scale[1]
        assert ranges.sun_intensity[0] <= scene.sun.intensity <= ranges.sun_intensity[1]
    fixed = SceneSettings(preset="varied", fish_shoals=[3, 3], dolphin_scale=[1.1, 1.1], particles=[])
    scene = draw_episode_scene(fixed, np.random.default_rng(4))
    base = draw_episode_scene(VARIED, np.random.default_rng(4))
    assert len(scene.shoals) == 3 and scene.dolphin_scale == 1.1 and len(scene.particles) == 0
    assert np.array_equal(scene.rocks, base.rocks) and scene.sun == base.sun  # the others drew the same
    dark = draw_episode_scene(
        SceneSettings(preset="varied", sun_intensity=[], sun_elevation_deg=[]), np.random.default_rng(4)
    )
    assert dark.sun is None and len(dark.shafts) == 0  # the shafts follow the sun
    assert np.array_equal(dark.particles, base.particles) and dark.dolphin_shade == base.dolphin_shade
    assert draw_episode_scene(SceneSettings(), np.random.default_rng(4)).plain


def test_bad_scene_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="scene: unknown setting 'fishes'; did you mean fish_"):
        SceneSettings.from_mapping({"fishes": [1, 2]})
    with pytest.raises(ValueError, match="unknown scene preset 'lush'"):
        SceneSettings.from_mapping({"preset": "lush"})
    with pytest.raises(ValueError, match="fish_shoals may ask for at most 3"):
        SceneSettings.from_mapping({"fish_shoals": [1, 9]})
    with pytest.raises(ValueError, match=r"sun_elevation_deg must lie in \[10.0, 90\]"):
        SceneSettings.from_mapping({"sun_elevation_deg": [0.0, 30.0]})
    with pytest.raises(ValueError, match="relief_m must be"):
        SceneSettings.from_mapping({"relief_m": [2.0, 1.0]})
    with pytest.raises(ValueError, match="unknown seabed textures"):
        World(WorldSettings(render=False, scene=SceneSettings(seabed_textures=["lava"])))
    with pytest.raises(ValueError, match="'scene' must be a map"):
        scene_option("varied")
    assert scene_option({"preset": "varied"}) == VARIED and scene_option(None) is None


def test_fish_and_scenery_touch_nothing(world):
    scenery = world.model.geom_bodyid == world.model.body("scenery").id
    assert not world.model.geom_contype[scenery].any() and not world.model.geom_conaffinity[scenery].any()
    crowded = SceneSettings(preset="varied", fish_shoals=[3, 3], fish_per_shoal=[8, 8], particles=[60, 60])
    world.reset(3, scene=crowded)
    world.scenery._movers.anchors[:] = world.data.qpos[:3]  # every fish and particle swims through the rover
    for action in actions(30):
        telemetry, _ = world.step(action)
        touched = world.data.contact.geom[: world.data.ncon].ravel()
        assert not np.isin(touched, np.flatnonzero(scenery)).any() and not telemetry.collided
    world.reset(3, scene=SceneSettings())


def test_a_varied_dataset_keeps_the_plain_datasets_labels(tmp_path):
    plain = write_dataset(tmp_path / "plain", 4, 9, progress=False)
    varied = write_dataset(tmp_path / "varied", 4, 9, world_settings=WorldSettings(scene=VARIED), progress=False)
    for name in ("labels", "poses"):
        assert np.array_equal(np.load(plain / f"shard-00000.{name}.npy"), np.load(varied / f"shard-00000.{name}.npy"))
    images = [np.load(path / "shard-00000.images.npy") for path in (plain, varied)]
    assert all(not np.array_equal(a, b) for a, b in zip(*images, strict=True))


@pytest.mark.slow
def test_a_live_sims_reset_takes_a_scene_map(processes, namespace):
    """Real processes: a router and `swimm sim`; the frame a reset with a ``scene`` map answers is the in-process
    varied world's, and a bad key comes back as the reset's refusal, naming it."""
    endpoint = processes.start_router()
    processes.start("sim", "sim", "--connect", endpoint, "--namespace", namespace, "--eval-envs", "0")
    settings = ZenohSettings(connect=[endpoint], namespace=namespace)
    session = open_session(settings, role="test")
    keys, holder = Keys(namespace), "learner-scene-test"
    token = announce(session, keys, "learner", holder)
    frames: queue.Queue[ObservationMsg] = queue.Queue()
    subscriber = session.declare_subscriber(
        keys.obs("train", "0", "direct"),
        lambda sample: [
            frames.put(obs) for _, obs in batch_messages(sample.payload.to_bytes(), ObservationMsg.from_item)
        ],
    )
    try:
        sims = Roster(session, keys, "sim")
        sims.wait_for(1, timeout_s=60)
        ctl = keys.ctl("train", "0")
        control.request(session, ctl, ClaimRequest(holder), timeout_s=30)
        control.request(session, ctl, ResetRequest(holder, ep=1, seed=21, scene={"preset": "varied"}), timeout_s=30)
        live = frames.get(timeout=30).image
        with pytest.raises(control.ControlError, match="reset's scene: unknown setting 'fishes'"):
            control.request(session, ctl, ResetRequest(holder, ep=2, seed=21, scene={"fishes": 1}), timeout_s=30)
        sims.close()
    finally:
        subscriber.undeclare()
        token.undeclare()
        session.close()
    inprocess = World(WorldSettings(scene=VARIED))
    try:
        assert np.array_equal(live, inprocess.reset(21)[1])
    finally:
        inprocess.close()
