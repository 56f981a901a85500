"""Click to reach without a browser: ray casts against a session's scene, the height rules, the paths, and the
whole click recipe (click, Down, Close, Up, click, Down, Open) driving the simulator on every robot and scene."""

from __future__ import annotations

import numpy as np
import pytest

from studio.backend.scene_state import body_poses, scene_geometry
from studio.sim.env import make_env
from studio.ui.reach import (
    HeightRules,
    SceneModel,
    down_height,
    min_jerk,
    object_label,
    path_duration,
    path_targets,
    ray_triangles,
)


def _scene(scene: str, robot: str, task: str, seed: int = 0):
    env = make_env(scene, robot, image_size=(60, 80))
    env.reset(task, seed)
    return env, SceneModel(scene_geometry(env.model), robot)


@pytest.fixture(scope="module")
def pick_place():
    env, model = _scene("pick_place", "sawyer", "pick_place/cube->red")
    yield env, model
    env.close()


def test_objects_are_the_small_movable_bodies_not_the_robot_table_or_zones(pick_place):
    _, model = pick_place
    assert model.objects == {"obj_cube", "obj_cylinder", "obj_prism", "obj_bar"}
    env, push = _scene("push", "panda", "push/blue-backward")
    assert push.objects == {"obj_red", "obj_blue"}
    env.close()


def test_the_status_line_names_objects_and_zones_as_a_person_does():
    assert [object_label(b) for b in ("obj_cube", "target_red", "table")] == ["cube", "red zone", "table"]


def test_a_ray_down_meets_the_top_of_each_object_and_the_table_elsewhere(pick_place):
    env, model = pick_place
    poses = body_poses(env.data)
    for name, p in model.object_positions(poses).items():
        hit = model.cast(poses, p + np.array([0.0, 0.0, 0.5]), (0.0, 0.0, -1.0))
        assert hit is not None and hit.body == name and hit.is_object
        assert hit.point[2] > p[2] + 0.01, f"{name}: the top, above the centre"
    hit = model.cast(poses, (0.3, 0.2, 0.5), (0.0, 0.0, -1.0))
    assert hit is not None and hit.body == "table" and not hit.is_object and abs(hit.point[2]) < 1e-6
    assert model.cast(poses, (0.3, 0.2, 0.5), (0.0, 0.0, 1.0)) is None, "nothing above the table"


def test_the_robot_is_never_hit(pick_place):
    env, model = pick_place
    poses = body_poses(env.data)
    ee = env.ee_pos
    hit = model.cast(poses, ee + np.array([0.0, 0.0, 0.3]), (0.0, 0.0, -1.0))
    assert hit is not None and hit.body == "table", "the ray passes through the gripper to the table"


def test_ray_triangles_hits_both_faces_and_misses_outside():
    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    assert ray_triangles(np.array([0.2, 0.2, 1.0]), np.array([0.0, 0.0, -1.0]), tri) == pytest.approx(1.0)
    assert ray_triangles(np.array([0.2, 0.2, -2.0]), np.array([0.0, 0.0, 1.0]), tri) == pytest.approx(2.0)
    assert ray_triangles(np.array([0.9, 0.9, 1.0]), np.array([0.0, 0.0, -1.0]), tri) == np.inf
    assert ray_triangles(np.array([0.2, 0.2, 1.0]), np.array([0.0, 0.0, 1.0]), tri) == np.inf


def test_paths_are_smooth_and_end_at_the_goal():
    a, b = np.zeros(3), np.array([0.3, 0.0, 0.0])
    targets = path_targets(a, b)
    assert np.allclose(targets[-1], b)
    assert np.all(np.diff(targets[:, 0]) >= 0), "monotonic"
    steps = np.diff(np.vstack([a, targets])[:, 0])
    assert steps[0] < steps[len(steps) // 2] and steps[-1] < steps[len(steps) // 2], "slow at both ends"
    assert path_duration(a, b) == pytest.approx(1.0) and path_duration(a, a) > 0
    assert np.allclose(min_jerk(a, b, 0.5), b / 2)


def test_down_goes_to_grasp_height_over_an_object_and_to_the_table_elsewhere(pick_place):
    env, model = pick_place
    poses = body_poses(env.data)
    rules = HeightRules("sawyer")
    rules.remember_rest(model.object_positions(poses))
    cube = model.object_positions(poses)["obj_cube"]
    z, why = down_height(model, rules, poses, np.array([cube[0], cube[1], 0.2]), 0.0)
    assert z == pytest.approx(max(cube[2], rules.lowest)) and "cube" in why
    z, why = down_height(model, rules, poses, np.array([0.3, 0.2, 0.2]), 0.0)
    assert z == pytest.approx(rules.lowest) and "table" in why
    # Holding the cube at carrying height over another place: Down sets it where it rested, 1 cm up.
    objects = dict(model.object_positions(poses), obj_cube=np.array([0.3, 0.2, 0.15]))
    assert rules.held(np.array([0.3, 0.2, 0.15]), 1.0, objects) == "obj_cube"
    assert rules.held(np.array([0.3, 0.2, 0.15]), 0.0, objects) is None, "an open gripper holds nothing"
    z, why = rules.down(np.array([0.3, 0.2, 0.15]), 1.0, objects, 0.0)
    assert z == pytest.approx(max(cube[2], rules.lowest) + 0.01) and "placing the cube" in why
    # The cube slipped 2 cm down in the fingers: the grasp point stops 2 cm higher, where the cube rests.
    objects["obj_cube"] = np.array([0.3, 0.2, 0.13])
    z, why = rules.down(np.array([0.3, 0.2, 0.15]), 1.0, objects, 0.0)
    assert z == pytest.approx(max(cube[2] + 0.02, rules.lowest) + 0.01) and "placing the cube" in why


class _Clicker:
    """The panel's click recipe on a bare simulator: targets along paths at the session's rates."""

    def __init__(self, env, model: SceneModel, robot: str):
        self.env, self.model, self.rules = env, model, HeightRules(robot)
        self.rules.remember_rest(model.object_positions(body_poses(env.data)), env.ee_pos)
        self.target, self.grip = env.ee_pos.copy(), 0.0

    def go(self, goal, hold: int = 20) -> None:
        for p in path_targets(self.target, np.asarray(goal, dtype=np.float64)):
            for _ in range(2):  # targets at 50 Hz, control ticks at 100 Hz
                self.env.step(p, self.grip)
            self.target = p
        for _ in range(hold):
            self.env.step(self.target, self.grip)

    def click(self, point) -> None:
        self.go([point[0], point[1], self.target[2]])

    def down(self) -> str:
        z, why = down_height(self.model, self.rules, body_poses(self.env.data), self.env.ee_pos, self.grip)
        self.go([self.target[0], self.target[1], z])
        return why

    def up(self) -> None:
        self.go([self.target[0], self.target[1], self.rules.up(self.env.ee_pos)])

    def gripper(self, closed: float) -> None:
        self.grip = closed
        self.go(self.target, hold=40)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scene", "robot", "task"),
    [
        ("pick_place", "sawyer", "pick_place/cube->red"),
        ("pick_place", "panda", "pick_place/bar->blue"),
        ("pick_place", "hand", "pick_place/cylinder->green"),
        ("push", "sawyer", "push/blue-backward"),
        ("push", "panda", "push/red-forward"),
        ("push", "hand", "push/red-backward"),
    ],
)
def test_the_click_recipe_succeeds_on_every_robot(scene, robot, task):
    from studio.sim.tasks import get_task

    env, model = _scene(scene, robot, task, seed=3)
    try:
        t, person = get_task(task), _Clicker(env, model, robot)
        obj = env.object_poses()[t.obj][:3]
        if scene == "pick_place":
            person.click(obj)
            assert "grasp height" in person.down()
            person.gripper(1.0)
            person.up()
            person.click(env.layout.target_pos[t.target])
            assert "placing" in person.down()
            person.gripper(0.0)
        else:
            sign = 1.0 if t.target == "forward" else -1.0
            person.click([obj[0], obj[1] - sign * 0.12, 0.0])
            person.gripper(1.0)
            assert "table" in person.down()
            person.click([obj[0], obj[1] + sign * 0.18, 0.0])
        assert env.success(), f"{task} with the {robot}"
    finally:
        env.close()


@pytest.mark.slow
def test_clicks_grasp_and_lift_a_meta_world_object():
    env, model = _scene("metaworld", "sawyer", "metaworld/pick-place-v3", seed=0)
    try:
        (name,) = model.objects
        person = _Clicker(env, model, "sawyer")
        obj = model.object_positions(body_poses(env.data))[name]
        person.click(obj)
        assert name in person.down()
        person.gripper(1.0)
        person.up()
        lifted = model.object_positions(body_poses(env.data))[name]
        assert lifted[2] > obj[2] + 0.05, f"the {name} is lifted: {lifted}"
    finally:
        env.close()
