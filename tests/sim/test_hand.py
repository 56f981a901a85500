"""The human hand: its model, how it looks, its pinch grasp, its state, its contacts and its scripted experts."""

import mujoco
import numpy as np
import pytest

from studio.sim import hand, robots, scenes
from studio.sim.experts import run_expert
from studio.sim.recording import embodiment_of, robot_of
from studio.sim.tasks import list_tasks

TASK = "pick_place/cube->red"


def _hand_geoms(model: mujoco.MjModel) -> list[int]:
    return [g for g in range(model.ngeom) if model.body(model.geom_bodyid[g]).name.startswith("hand")]


def _grasp_cube(env, seed: int = 0, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Reset, bring the open hand down over the cube (plus ``offset``), close; the cube's start position."""
    env.reset(TASK, seed)
    cube = env.object_poses()["cube"][:3]
    at = cube + np.asarray(offset)
    for _ in range(40):
        env.step(at + np.array([0.0, 0.0, 0.12]), 0.0)
    for _ in range(40):
        env.step(at, 0.0)
    for _ in range(15):
        env.step(at, 1.0)
    return cube


def test_model_compiles_with_its_parts():
    model = scenes.build_model("pick_place", "hand")
    info = robots.robot_info("hand")
    assert model.nmocap == 1 and model.nu == len(hand.FINGER_JOINTS) == 15
    assert model.site(info.grasp_site).id >= 0 and model.camera(info.wrist_camera).id >= 0
    welds = [
        model.equality(i).name
        for i in range(model.neq)
        if model.equality(i).name.startswith(hand.WELD_PREFIX)
    ]
    assert sorted(welds) == sorted(hand.WELD_PREFIX + o for o in scenes.scene_info("pick_place").objects)
    assert not any(model.eq_active0[model.equality(w).id] for w in welds)
    skin = [model.geom_rgba[g] for g in _hand_geoms(model) if model.geom(g).name.startswith("hand_index")]
    assert skin and np.allclose(skin[0], [0.87, 0.68, 0.55, 1.0])
    # A forearm behind and above the wrist, reaching out of the picture.
    forearm = model.geom("hand_upper_arm")
    assert forearm.size[0] > 0.03
    assert embodiment_of("hand") == "human" and robot_of("human") == "hand" and robot_of("panda") == "panda"
    alone = scenes.build_robot_model("hand")
    assert alone.nu == 15 and alone.neq == 1  # only the mocap weld: no objects to grasp


def test_renders_skin_coloured_hand_in_external_camera(env_factory):
    env = env_factory("pick_place", "hand")
    env.reset(TASK, 0)
    for _ in range(60):
        env.step(np.array([0.0, 0.5, 0.08]), 0.0)
    rgb = env.render()
    r = mujoco.Renderer(env.model, *env.image_size)
    try:
        r.enable_segmentation_rendering()
        r.update_scene(env.data, camera="external")
        seg = r.render()
    finally:
        r.close()
    ids = set(_hand_geoms(env.model))
    skin_rgba = [float(v) for v in hand.SKIN_RGBA.split()]
    skin_geoms = {g for g in ids if np.allclose(env.model.geom_rgba[g], skin_rgba)}
    is_hand = np.isin(seg[..., 0], list(ids)) & (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM))
    is_skin = np.isin(seg[..., 0], list(skin_geoms)) & is_hand
    assert is_hand.sum() > 1500, "the hand and forearm fill a good part of the picture"
    assert is_skin.sum() > 0.6 * is_hand.sum(), "most of what shows is skin (the rest is the sleeve)"
    r_, g_, b_ = rgb[is_skin].astype(float).mean(axis=0)
    # Lit skin: red over green over blue, green about 40 % of the way from blue to red (0.87, 0.68, 0.55).
    assert r_ > 180 and r_ - b_ > 40 and 0.3 < (g_ - b_) / (r_ - b_) < 0.55, (
        f"not skin-coloured: {(r_, g_, b_)}"
    )


def test_fingers_curl_into_a_pinch(env_factory):
    env = env_factory("pick_place", "hand")
    env.reset(TASK, 0)
    target = np.array([0.0, 0.5, 0.15])
    for _ in range(30):
        env.step(target, 0.0)
    open_width, open_q = env.gripper_opening(), env.state()["qpos"][3:].copy()
    for _ in range(30):
        env.step(target, 1.0)
    closed_width, closed_q = env.gripper_opening(), env.state()["qpos"][3:]
    assert open_width > 0.10 and 0.05 < closed_width < 0.065
    assert np.allclose(open_q, 0.0, atol=0.02)
    assert np.allclose(closed_q, hand.CLOSED_POSE, atol=0.05)
    # The outer fingers curl most, towards the palm.
    assert closed_q[hand.FINGER_JOINTS.index("hand_middle2")] > 1.0
    for _ in range(30):
        env.step(target, 0.0)
    assert env.gripper_opening() > 0.10


def test_pinch_lifts_the_object_and_lets_it_go(env_factory):
    env = env_factory("pick_place", "hand")
    cube = _grasp_cube(env, 0, offset=(0.004, -0.003, 0.002))
    assert np.linalg.norm(env.object_poses()["cube"][:3] - cube) < 0.002, (
        "approach and closing moved the cube"
    )
    assert env.held_object() == "cube"
    rel = env.object_poses()["cube"][:3] - env.ee_pos
    for _ in range(60):
        env.step(cube + np.array([0.0, 0.1, 0.15]), 1.0)
    lifted = env.object_poses()["cube"][:3]
    assert lifted[2] > 0.14 and np.allclose(lifted - env.ee_pos, rel, atol=0.002)
    assert env.stages()["grasped"]
    for _ in range(40):
        env.step(env.target, 0.0)
    assert env.held_object() is None
    assert env.object_poses()["cube"][2] < 0.025, "released, the cube falls back onto the table"


def test_closing_away_from_objects_grasps_nothing(env_factory):
    env = env_factory("pick_place", "hand")
    env.reset(TASK, 0)
    cube = env.object_poses()["cube"][:3]
    for _ in range(60):
        env.step(
            cube + np.array([0.0, 0.0, 0.06]), 1.0
        )  # closed the whole way down: no rising edge at the cube
    assert env.held_object() is None
    for _ in range(10):
        env.step(cube + np.array([0.0, 0.0, 0.06]), 0.0)
    for _ in range(10):
        env.step(cube + np.array([0.0, 0.0, 0.06]), 1.0)  # closing 6 cm above: too far
    assert env.held_object() is None


def test_restored_state_keeps_the_object_welded(env_factory):
    env = env_factory("pick_place", "hand")
    m, d = env.model, env.data
    cube = _grasp_cube(env, 1, offset=(0.006, 0.0, 0.0))
    for _ in range(40):
        env.step(cube + np.array([0.0, 0.0, 0.12]), 1.0)
    rel_saved = env.object_poses()["cube"][:3] - env.ee_pos
    kind = mujoco.mjtState.mjSTATE_INTEGRATION
    saved = np.empty(mujoco.mj_stateSize(m, kind))
    mujoco.mj_getState(m, d, saved, kind)
    # Put it down, grasp it again with another offset (the weld's relative pose changes), then go back in time.
    for _ in range(40):
        env.step(cube + np.array([0.0, 0.0, 0.02]), 1.0)
    for _ in range(20):
        env.step(env.target, 0.0)
    again = env.object_poses()["cube"][:3]
    for _ in range(20):
        env.step(again + np.array([-0.008, 0.0, 0.0]), 0.0)
    for _ in range(10):
        env.step(again + np.array([-0.008, 0.0, 0.0]), 1.0)
    assert env.held_object() == "cube"
    assert not np.allclose(env.object_poses()["cube"][:3] - env.ee_pos, rel_saved, atol=0.005)
    mujoco.mj_setState(m, d, saved, kind)
    env.controller.sync(d)
    mujoco.mj_forward(m, d)
    assert env.held_object() == "cube"
    for _ in range(60):
        env.step(cube + np.array([0.1, 0.15, 0.2]), 1.0)
    cube_now = env.object_poses()["cube"][:3]
    assert cube_now[2] > 0.18 and np.allclose(cube_now - env.ee_pos, rel_saved, atol=0.002)


def test_push_scene_touches_objects_only_through_the_proxy():
    model = scenes.build_model("push", "hand")
    pusher = model.geom(hand.PUSHER_GEOM).id
    assert model.geom_contype[pusher] == 2 and model.geom_group[pusher] == 3
    others = [g for g in _hand_geoms(model) if g != pusher]
    assert not any(model.geom_contype[g] or model.geom_conaffinity[g] for g in others)
    for o in scenes.scene_info("push").objects:
        assert model.geom_conaffinity[model.geom(f"obj_{o}").id] & 2
    assert not model.geom_conaffinity[model.geom("table_top").id] & 2
    assert not any(model.equality(i).name.startswith(hand.WELD_PREFIX) for i in range(model.neq))
    pick = scenes.build_model("pick_place", "hand")
    assert not any(pick.geom_contype[g] or pick.geom_conaffinity[g] for g in _hand_geoms(pick))


def test_wrist_camera_sees_the_table(env_factory):
    env = env_factory("pick_place", "hand")
    env.reset(TASK, 0)
    for _ in range(60):
        env.step(np.array([0.0, 0.5, 0.15]), 0.0)
    depth = env.render_depth("wrist")
    assert depth.shape == env.depth_size and np.all(np.isfinite(depth))
    assert 0.1 < float(np.median(depth)) < 0.4


@pytest.mark.parametrize("scene", ["pick_place", "push"])
def test_scripted_experts_succeed(env_factory, scene):
    env = env_factory(scene, "hand")
    failures = []
    for i, task in enumerate(list_tasks(scene)):
        for seed in (7 * i, 7 * i + 1, 7 * i + 2):
            env.reset(task, seed)
            if not run_expert(env):
                failures.append((task, seed, env.stages()))
    assert not failures
