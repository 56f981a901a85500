"""Scene composition: every robot in both scenes, with the properties the simulator relies on."""

import mujoco
import numpy as np
import pytest

from studio.sim import robots, scenes


@pytest.mark.parametrize("scene", ["pick_place", "push"])
@pytest.mark.parametrize("robot", ["panda", "sawyer", "hand"])
def test_robot_loads_in_scene(scene, robot):
    model = scenes.build_model(scene, robot)
    info = robots.robot_info(robot)
    assert model.site(info.grasp_site).id >= 0
    assert model.camera("external").id >= 0 and model.camera(info.wrist_camera).id >= 0
    for o in scenes.scene_info(scene).objects:
        assert model.body(f"obj_{o}").mass[0] > 0.01, "objects must have mass (inertiagrouprange)"
    robot_bodies = [
        model.body(i) for i in range(model.nbody) if model.body(i).name.startswith(info.body_prefix)
    ]
    assert robot_bodies and all(model.body_gravcomp[b.id] == 1.0 for b in robot_bodies)
    if robot == "sawyer":
        assert model.nmocap == 1
    elif robot == "hand":
        assert model.nmocap == 1 and model.nu == 15
    else:
        assert model.nu == 9


def test_unknown_names_give_clear_errors():
    with pytest.raises(ValueError, match="unknown scene"):
        scenes.build_model("kitchen", "panda")
    with pytest.raises(ValueError, match="unknown robot"):
        scenes.build_model("push", "ur5")


def test_panda_holds_still_under_gravity():
    """Gravity compensation + joint position control: the arm does not sag over 2 s."""
    model = scenes.build_model("push", "panda")
    data = mujoco.MjData(model)
    from studio.sim.ik import PandaIK

    ik = PandaIK(model)
    ik.reset(data)
    mujoco.mj_forward(model, data)
    start = data.site("grasp_site").xpos.copy()
    mujoco.mj_step(model, data, nstep=1000)
    assert np.linalg.norm(data.site("grasp_site").xpos - start) < 0.003
