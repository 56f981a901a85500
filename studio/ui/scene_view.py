"""One browser tab's 3D scene: the simulated bodies, the external camera, and plan / path overlays.

The bodies come from a :class:`~studio.backend.messages.SceneGeometry` (sent by the sim worker, or built
from the scene files for replays): one viser frame per body that carries geoms, the geoms as meshes under
it in their body-local poses, all under a root frame named afresh for every load (see :meth:`SceneView._fresh`). A pose update moves the body frames only, and only those that moved visibly
(:data:`POSITION_EPS`, :data:`QUATERNION_EPS`) since the pose last *sent* for them — so slow motion still shows
and contact chatter does not (a cylinder resting on the table rocks by ~0.05° at every tick, which made the
browser redraw at 60 Hz forever) — all inside one ``client.atomic()`` block so the browser applies a whole tick
at once.

The external camera is drawn as a frustum (OpenCV convention, like :class:`studio.sim.camera.CameraModel`)
showing its latest image. Overlays: the 5 waypoints of a plan (spheres coloured by gripper state, joined
by a spline, the current one enlarged), end-effector paths (splines, one colour per gripper state, or one colour per
path) and markers (spheres that move).

Meshes are shown with at most :data:`MAX_FACES` triangles each (quadric decimation, computed once per mesh):
the robot models' visual meshes have 7,000–21,000 triangles per link (130,000 for the Panda), and without a GPU
the browser redraws all of them on the CPU for every pose frame (`studio bench ui` measures what that costs).
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Sequence

import numpy as np
import trimesh
import viser
import viser.transforms as vtf

from studio.backend import messages as msg

#: A body is re-sent once it is this far (metres) from the position last sent for it …
POSITION_EPS = 5e-4
#: … or any quaternion component is this far from the last sent one (about 0.2° of rotation).
QUATERNION_EPS = 2e-3
OPEN_RGB = (40, 170, 90)
CLOSED_RGB = (220, 70, 40)
PLAN_RGB = (250, 200, 40)
#: A guided policy's plan from the null demonstration (the scene alone), drawn beside the plan.
NULL_PLAN_RGB = (150, 150, 160)
PATH_RGB = {"open": (60, 130, 230), "closed": (235, 140, 30)}
#: Triangle budget per mesh in the browser (None: the scene's own meshes).
MAX_FACES: int | None = 2000
_decimated: dict[tuple, trimesh.Trimesh] = {}
_decimated_lock = threading.Lock()


def geom_mesh(
    geom: msg.GeomSpec, meshes: Sequence[msg.MeshSpec], max_faces: int | None = None
) -> trimesh.Trimesh | None:
    """The geom's surface in its own frame (None for types a viewer does not draw, e.g. height fields).

    A mesh with more than ``max_faces`` triangles is decimated to about that many (cached per mesh content)."""
    size = np.asarray(geom.size, dtype=np.float64)
    if geom.type == "mesh" and geom.mesh >= 0:
        spec = meshes[geom.mesh]
        verts = np.frombuffer(spec.vertices, dtype="<f4").reshape(-1, 3)
        faces = np.frombuffer(spec.faces, dtype="<i4").reshape(-1, 3)
        if max_faces is None or len(faces) <= max_faces:
            return trimesh.Trimesh(verts.copy(), faces.copy(), process=False)
        return decimated(spec, max_faces)
    if geom.type == "box":
        return trimesh.creation.box(extents=2 * size)
    if geom.type == "sphere":
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    if geom.type == "cylinder":
        return trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=24)
    if geom.type == "capsule":
        return trimesh.creation.capsule(radius=size[0], height=2 * size[1], count=[12, 12])
    if geom.type == "ellipsoid":
        s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        s.apply_scale(size)
        return s
    if geom.type == "plane":
        return trimesh.creation.box(extents=[2 * (size[0] or 2.0), 2 * (size[1] or 2.0), 0.002])
    return None


def decimated(spec: msg.MeshSpec, max_faces: int) -> trimesh.Trimesh:
    """``spec``'s mesh with about ``max_faces`` triangles (quadric decimation; computed once per content)."""
    key = (hashlib.blake2b(spec.vertices + spec.faces, digest_size=16).digest(), max_faces)
    with _decimated_lock:
        if key in _decimated:
            return _decimated[key].copy()
    verts = np.frombuffer(spec.vertices, dtype="<f4").reshape(-1, 3).astype(np.float64)
    faces = np.frombuffer(spec.faces, dtype="<i4").reshape(-1, 3)
    mesh = trimesh.Trimesh(verts, faces, process=True)  # merge duplicate vertices so edges can collapse
    mesh = mesh.simplify_quadric_decimation(face_count=max_faces)
    with _decimated_lock:
        _decimated[key] = mesh
    return mesh.copy()


def camera_pose(camera: dict) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(position, wxyz, vertical fov in radians, aspect) of a :meth:`CameraModel.to_dict` camera."""
    T = np.asarray(camera["T_world_cam"], dtype=np.float64)
    K = np.asarray(camera["K"], dtype=np.float64)
    w, h = float(camera["width"]), float(camera["height"])
    fov = 2.0 * np.arctan2(h / 2.0, K[1, 1])
    return T[:3, 3], vtf.SO3.from_matrix(T[:3, :3]).wxyz, float(fov), w / h


class SceneView:
    """The scene of one client (a tab). Thread-safe: poses arrive on a pump thread, overlays from callbacks."""

    def __init__(self, client: viser.ClientHandle, root: str = "/sim"):
        self.client = client
        self.scene = client.scene
        self.root = root
        self.key: object = None
        self.body_names: tuple[str, ...] = ()
        self._bodies: dict[int, viser.FrameHandle] = {}
        self._nodes: list = []
        self._scene_root: viser.FrameHandle | None = None
        self._generation = 0  # numbers the loads: no body or geom name is ever created twice
        self._sent: np.ndarray | None = None
        self._lock = threading.RLock()
        self._frustum: viser.CameraFrustumHandle | None = None
        self._camera_key: tuple | None = None
        self._overlays: dict[str, list[viser.SceneNodeHandle]] = {}
        self.updates_sent = 0
        self.faces_shown = 0

    # ------------------------------------------------------------------ bodies
    def load(self, geometry: msg.SceneGeometry, key: object) -> None:
        """Show ``geometry`` (replacing what was shown unless ``key`` says it is the same scene)."""
        with self._lock:
            if key == self.key and self._bodies:
                self._sent = None  # the next pose update re-sends every body
                return
            self._clear_bodies()
            self.key = key
            budget = MAX_FACES
            self.body_names = geometry.body_names
            root = f"{self.root}/{self._fresh()}"
            with self.client.atomic():
                self._scene_root = self.scene.add_frame(root, show_axes=False)
                for i, g in enumerate(geometry.geoms):
                    rgba = np.asarray(g.rgba)
                    if rgba[3] < 0.05:
                        continue
                    mesh = geom_mesh(g, geometry.meshes, budget)
                    if mesh is None:
                        continue
                    self.faces_shown += len(mesh.faces)
                    body = self._bodies.get(g.body)
                    if body is None:
                        body = self.scene.add_frame(f"{root}/b{g.body}", show_axes=False)
                        self._bodies[g.body] = body
                    node = self.scene.add_mesh_simple(
                        f"{root}/b{g.body}/g{i}",
                        mesh.vertices.astype(np.float32),
                        mesh.faces.astype(np.uint32),
                        color=(int(255 * rgba[0]), int(255 * rgba[1]), int(255 * rgba[2])),
                        opacity=float(rgba[3]) if rgba[3] < 1 else None,
                        flat_shading=g.type != "mesh",
                        cast_shadow=False,
                        receive_shadow=False,
                        position=g.pos,
                        wxyz=g.quat,
                    )
                    self._nodes.append(node)
            self._sent = None

    def _fresh(self) -> str:
        """A name part never used before by this view.

        A node created under the name of one removed a moment earlier is not a new node to the browser: viser
        lets the create supersede the pending removal, and the browser keeps the old node's pose wherever the new
        node's pose is viser's default (the identity, never sent). Bodies resting at the origin and geoms at
        their body's origin then showed the previous scene's poses (a tilted pedestal, a tabletop and zones
        elsewhere). A fresh root name makes every load a new set of nodes."""
        self._generation += 1
        return f"v{self._generation}"

    def _clear_bodies(self) -> None:
        if self._scene_root is not None:
            self._scene_root.remove()  # removes every body and geom under it
            self._scene_root = None
        self._nodes.clear()
        self._bodies.clear()
        self.faces_shown = 0
        self.key = None
        self._sent = None

    def apply(self, poses: np.ndarray) -> int:
        """Move the bodies to ``poses`` ((B, 7) xyz + wxyz); returns how many bodies were sent."""
        poses = np.asarray(poses, dtype=np.float32)
        with self._lock:
            if not self._bodies:
                return 0
            if self._sent is None or self._sent.shape != poses.shape:
                moved = list(self._bodies)
                self._sent = poses.copy()
            else:
                delta = np.abs(poses - self._sent)
                visible = (delta[:, :3].max(axis=1) > POSITION_EPS) | (
                    delta[:, 3:].max(axis=1) > QUATERNION_EPS
                )
                moved = [b for b in self._bodies if b < len(poses) and visible[b]]
            if moved:
                with self.client.atomic():
                    for b in moved:
                        if b < len(poses):
                            h = self._bodies[b]
                            h.position = poses[b, :3].astype(np.float64)
                            h.wxyz = poses[b, 3:].astype(np.float64)
                            self._sent[b] = poses[b]
                self.updates_sent += 1
            return len(moved)

    # ------------------------------------------------------------------ camera
    def set_camera(self, camera: dict, image: np.ndarray | None = None) -> None:
        """Draw the external camera (``CameraModel.to_dict()``), with ``image`` on its frustum if given."""
        pos, wxyz, fov, aspect = camera_pose(camera)
        key = (tuple(np.round(pos, 6)), tuple(np.round(wxyz, 6)), round(fov, 6), round(aspect, 6))
        with self._lock:
            if self._frustum is not None and key == self._camera_key:
                if image is not None:
                    self._frustum.image = image
                return
            if self._frustum is not None:
                self._frustum.remove()
            self._frustum = self.scene.add_camera_frustum(
                f"{self.root}_camera",
                fov=fov,
                aspect=aspect,
                scale=0.12,
                thickness=0.004,
                color=(60, 60, 60),
                image=image,
                jpeg_quality=70,
                position=pos,
                wxyz=wxyz,
            )
            self._camera_key = key

    def set_camera_image(self, image: np.ndarray) -> None:
        with self._lock:
            if self._frustum is not None:
                self._frustum.image = image

    # ------------------------------------------------------------------ overlays
    def clear_overlay(self, name: str) -> None:
        with self._lock:
            for h in self._overlays.pop(name, []):
                h.remove()

    def show_waypoints(
        self,
        name: str,
        waypoints: np.ndarray,
        current: int | None = None,
        color: tuple[int, int, int] = PLAN_RGB,
        faint: bool = False,
    ) -> None:
        """The 5 waypoints (rows xyz + gripper probability) as numbered spheres joined by a ``color`` spline;
        ``faint`` draws them half-transparent and smaller (a plan shown for comparison)."""
        wps = np.asarray(waypoints, dtype=np.float64).reshape(-1, 4)
        with self._lock:
            self.clear_overlay(name)
            handles: list[viser.SceneNodeHandle] = []
            with self.client.atomic():
                if len(wps) >= 2:
                    handles.append(
                        self.scene.add_spline_catmull_rom(
                            f"/overlay/{name}/spline",
                            wps[:, :3],
                            thickness=0.003 if faint else 0.004,
                            color=color,
                        )
                    )
                for i, row in enumerate(wps):
                    closed = row[3] > 0.5
                    big = current == i
                    handles.append(
                        self.scene.add_icosphere(
                            f"/overlay/{name}/wp{i}",
                            radius=0.028 if big else 0.010 if faint else 0.013,
                            color=CLOSED_RGB if closed else OPEN_RGB,
                            position=row[:3],
                            opacity=0.35 if faint else None if big or current is None else 0.55,
                        )
                    )
                    if not faint:
                        handles.append(
                            self.scene.add_label(
                                f"/overlay/{name}/label{i}",
                                f"{i + 1}{' ●' if closed else ''}",
                                position=row[:3] + np.array([0.0, 0.0, 0.035]),
                                font_screen_scale=0.8,
                            )
                        )
            self._overlays[name] = handles

    def show_null_plan(self, waypoints: np.ndarray | None) -> None:
        """A guided policy's plan from the scene alone, faint and grey beside the plan; None clears it."""
        if waypoints is None:
            self.clear_overlay("null plan")
        else:
            self.show_waypoints("null plan", waypoints, color=NULL_PLAN_RGB, faint=True)

    def clear_overlays(self) -> None:
        """Remove every overlay (a new view starts clean)."""
        with self._lock:
            for name in list(self._overlays):
                self.clear_overlay(name)

    def show_marker(
        self, name: str, position: np.ndarray, color: tuple[int, int, int], radius: float = 0.016
    ) -> None:
        """A sphere at ``position``; called again with the same name it only moves (cheap enough for playback)."""
        pos = np.asarray(position, dtype=np.float64).reshape(3)
        with self._lock:
            handles = self._overlays.get(name)
            if handles and len(handles) == 1:
                handles[0].position = pos
                return
            self.clear_overlay(name)
            self._overlays[name] = [
                self.scene.add_icosphere(f"/overlay/{name}", radius=radius, color=color, position=pos)
            ]

    def show_path(
        self,
        name: str,
        points: np.ndarray,
        gripper: np.ndarray | None = None,
        color: tuple[int, int, int] | None = None,
    ) -> None:
        """An end-effector path as splines, one per run of equal gripper state (open blue, closed orange), or all in
        ``color`` when given (e.g. two rollouts' paths told apart by colour)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        closed = np.zeros(len(pts), bool) if gripper is None else np.asarray(gripper).reshape(-1) > 0.5
        with self._lock:
            self.clear_overlay(name)
            handles: list[viser.SceneNodeHandle] = []
            if len(pts) < 2:
                self._overlays[name] = handles
                return
            step = max(1, len(pts) // 200)  # a spline through ≤ ~200 points is plenty for the eye
            idx = np.unique(
                np.r_[np.arange(0, len(pts), step), np.flatnonzero(np.diff(closed)), len(pts) - 1]
            )
            with self.client.atomic():
                start = 0
                for k in range(1, len(idx) + 1):
                    if k == len(idx) or closed[idx[k]] != closed[idx[start]]:
                        end = min(k, len(idx) - 1)
                        seg = pts[idx[start : end + 1]]
                        if len(seg) >= 2:
                            rgb = color or PATH_RGB["closed" if closed[idx[start]] else "open"]
                            handles.append(
                                self.scene.add_spline_catmull_rom(
                                    f"/overlay/{name}/s{k}", seg, thickness=0.005, color=rgb
                                )
                            )
                        start = k
                handles.append(
                    self.scene.add_icosphere(
                        f"/overlay/{name}/start", radius=0.01, color=(255, 255, 255), position=pts[0]
                    )
                )
            self._overlays[name] = handles

    def clear(self) -> None:
        with self._lock:
            self.clear_overlays()
            self._clear_bodies()
            if self._frustum is not None:
                self._frustum.remove()
                self._frustum = None
