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
    box = msg.GeomSpec(
        body=0,
        type="box",
        group=0,
        size=(0.1, 0.2, 0.3),
        pos=(0, 0, 0),
        quat=(1, 0, 0, 0),
        rgba=(1, 1, 1, 1),
        mesh=-1,
    )
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


class _Handle:
    def __init__(self, name: str):
        self.name, self.position, self.wxyz, self.removed = name, None, None, False

    def remove(self) -> None:
        self.removed = True


class _FakeScene:
    def __init__(self):
        self.nodes: list[_Handle] = []

    def add_frame(self, name, **_):
        self.nodes.append(_Handle(name))
        return self.nodes[-1]

    def add_mesh_simple(self, name, vertices, faces, **_):
        self.nodes.append(_Handle(name))
        self.nodes[-1].faces = len(faces)
        return self.nodes[-1]


class _FakeClient:
    def __init__(self):
        self.scene = _FakeScene()

    def atomic(self):
        import contextlib

        return contextlib.nullcontext()


def _two_boxes() -> msg.SceneGeometry:
    box = dict(
        type="box",
        group=0,
        size=(0.02, 0.02, 0.02),
        pos=(0, 0, 0),
        quat=(1, 0, 0, 0),
        rgba=(1, 0, 0, 1),
        mesh=-1,
    )
    return msg.SceneGeometry(
        body_names=("a", "b"), geoms=(msg.GeomSpec(body=0, **box), msg.GeomSpec(body=1, **box)), meshes=()
    )


def test_pose_updates_send_visible_motion_only_and_never_lose_slow_drift():
    from studio.ui.scene_view import POSITION_EPS, QUATERNION_EPS, SceneView

    view = SceneView(_FakeClient())
    view.load(_two_boxes(), "k")
    poses = np.array([[0, 0, 0, 1, 0, 0, 0], [0.1, 0, 0, 1, 0, 0, 0]], dtype=np.float64)
    assert view.apply(poses) == 2  # the first update sends every body
    rng = np.random.default_rng(0)
    for _ in range(50):  # contact chatter: both bodies rock far below what a pixel shows
        jitter = poses.copy()
        jitter[:, 3:] += rng.uniform(-0.4, 0.4, (2, 4)) * QUATERNION_EPS
        jitter[:, :3] += rng.uniform(-0.4, 0.4, (2, 3)) * POSITION_EPS
        assert view.apply(jitter) == 0
    assert view.updates_sent == 1
    # body b drifts by 0.3 of the threshold per tick: each tick alone is invisible, the sum is not
    sent_at = []
    for k in range(1, 14):
        step = poses.copy()
        step[1, 0] += k * 0.3 * POSITION_EPS
        if view.apply(step):
            sent_at.append(k)
    assert sent_at == [4, 8, 12], (
        sent_at
    )  # re-sent as soon as it is > POSITION_EPS from what the browser shows
    assert abs(view._bodies[1].position[0] - (0.1 + 12 * 0.3 * POSITION_EPS)) < 1e-6
    turned = step.copy()  # b stays where it is
    turned[0, 3:] = [np.cos(0.01), 0, 0, np.sin(0.01)]  # 1.1° about z
    assert view.apply(turned) == 1 and np.allclose(view._bodies[0].wxyz, turned[0, 3:])


def test_heavy_meshes_are_decimated_to_the_budget_keeping_their_shape():
    import trimesh

    from studio.ui import scene_view

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)  # 20,480 faces
    spec = msg.MeshSpec(
        name="ball",
        vertices=sphere.vertices.astype("<f4").tobytes(),
        faces=sphere.faces.astype("<i4").tobytes(),
    )
    geom = msg.GeomSpec(
        body=0,
        type="mesh",
        group=0,
        size=(0, 0, 0),
        pos=(0, 0, 0),
        quat=(1, 0, 0, 0),
        rgba=(1, 1, 1, 1),
        mesh=0,
    )
    full = scene_view.geom_mesh(geom, (spec,))
    light = scene_view.geom_mesh(geom, (spec,), max_faces=1000)
    assert len(full.faces) == 20480 and 500 <= len(light.faces) <= 1000
    np.testing.assert_allclose(light.bounds, full.bounds, atol=2e-3)
    assert abs(light.volume - full.volume) / full.volume < 0.02
    assert scene_view.geom_mesh(geom, (spec,), max_faces=1000) is not light  # a copy of the cached mesh
    assert len(scene_view.geom_mesh(geom, (spec,), max_faces=30000).faces) == 20480  # under budget: untouched

    view = scene_view.SceneView(_FakeClient())
    geometry = msg.SceneGeometry(body_names=("ball",), geoms=(geom,), meshes=(spec,))
    view.load(geometry, "k")
    assert view.faces_shown <= scene_view.MAX_FACES


def test_a_new_scene_replaces_every_node_of_the_previous_one_under_names_never_used_before():
    """viser lets a node created under a just-removed name supersede the removal, and the browser then keeps the
    removed node's pose wherever the new one's is the default: a scene switch must never re-create a name."""
    import viser

    from studio.backend import bus
    from studio.ui.scene_view import SceneView

    server = viser.ViserServer(host="127.0.0.1", port=bus.free_loopback_port(), verbose=False)
    try:
        view = SceneView(server)  # the broadcast scene: the same scene API as a tab's client
        registry = server.scene._handle_from_node_name

        def shown() -> set[str]:
            return {n for n in registry if n.startswith("/sim/")}

        a, b = _two_boxes(), msg.SceneGeometry(body_names=("a",), geoms=_two_boxes().geoms[:1], meshes=())
        seen: set[str] = set()
        for geometry, key in ((a, "a"), (b, "b"), (a, "a")):
            view.load(geometry, key)
            view.apply(np.tile([0, 0, 0, 1, 0, 0, 0], (len(geometry.body_names), 1)))
            assert len([n for n in shown() if "/g" in n]) == len(geometry.geoms)
            assert not shown() & seen, f"names of an earlier scene re-created: {sorted(shown() & seen)}"
            seen |= shown()
        same = shown()
        view.load(a, "a")  # the same scene again: kept as it is
        assert shown() == same
        view.clear()
        assert not shown()
    finally:
        server.stop()
