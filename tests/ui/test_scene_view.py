"""Scene geometry for the browser: every geom type the worker sends becomes a mesh; camera poses in viser's frame."""

import numpy as np

from studio.backend import messages as msg
from studio.backend.replay import scene_snapshot
from studio.sim.camera import CameraModel
from studio.ui.scene_view import camera_pose, geom_mesh


def test_every_visual_geom_of_the_scenes_becomes_a_mesh():
    for scene, robot in (("pick_place", "panda"), ("push", "sawyer")):
        geometry, poses = scene_snapshot(
            scene, robot, f"{scene}/{'cube->red' if scene == 'pick_place' else 'red-forward'}", 0
        )
        assert poses.shape == (len(geometry.body_names), 7)
        for g in geometry.geoms:
            mesh = geom_mesh(g, geometry.meshes)
            assert mesh is not None and len(mesh.faces) > 0, (scene, g.type)
    box = msg.GeomSpec(body=0, type="box", group=0, size=(0.1, 0.2, 0.3), pos=(0, 0, 0), quat=(1, 0, 0, 0),
                       rgba=(1, 1, 1, 1), mesh=-1)  # fmt: skip
    np.testing.assert_allclose(geom_mesh(box, ()).extents, [0.2, 0.4, 0.6])
    hfield = msg.GeomSpec(**{**{f: getattr(box, f) for f in box.__struct_fields__}, "type": "hfield"})
    assert geom_mesh(hfield, ()) is None


def test_camera_pose_matches_the_camera_model():
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # looking along +y (z forward), y down = -z world
    T[:3, 3] = [0.1, -0.5, 0.4]
    pos, wxyz, fov, aspect = camera_pose(CameraModel(320, 240, K, T).to_dict())
    np.testing.assert_allclose(pos, [0.1, -0.5, 0.4])
    import viser.transforms as vtf

    np.testing.assert_allclose(vtf.SO3(wxyz).as_matrix(), T[:3, :3], atol=1e-9)
    assert fov == np.float64(2 * np.arctan(120 / 200)) and aspect == 320 / 240
