"""Mirrors a MuJoCo scene in viser: one mesh per visible geom, poses pushed in atomic batches.

Geometry comes from the compiled model (mesh geoms from their vertex/face buffers, primitives through
trimesh), so the browser shows exactly what the simulator simulates. Static geoms are sent once; only
geoms of moving bodies are updated.
"""

from __future__ import annotations

import mujoco
import numpy as np
import trimesh
import viser

G = mujoco.mjtGeom
#: Geom groups observation cameras and the browser show (3+ hold collision-only geometry).
VISIBLE_GROUPS = (0, 1, 2)


def geom_trimesh(model: mujoco.MjModel, g: int) -> trimesh.Trimesh | None:
    """The geom's surface in its own frame, or None for types the browser does not draw."""
    t, size = model.geom_type[g], model.geom_size[g]
    if t == G.mjGEOM_MESH:
        m = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[m], model.mesh_vertnum[m]
        f0, nf = model.mesh_faceadr[m], model.mesh_facenum[m]
        return trimesh.Trimesh(model.mesh_vert[v0 : v0 + nv].copy(), model.mesh_face[f0 : f0 + nf].copy(),
                               process=False)
    if t == G.mjGEOM_BOX:
        return trimesh.creation.box(extents=2 * size)
    if t == G.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    if t == G.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=24)
    if t == G.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(radius=size[0], height=2 * size[1], count=[12, 12])
    if t == G.mjGEOM_ELLIPSOID:
        s = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        s.apply_scale(size)
        return s
    if t == G.mjGEOM_PLANE:
        return trimesh.creation.box(extents=[2 * (size[0] or 3.0), 2 * (size[1] or 3.0), 0.002])
    return None


def geom_rgba(model: mujoco.MjModel, g: int) -> np.ndarray:
    mat = model.geom_matid[g]
    return model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]


def _moving_bodies(model: mujoco.MjModel) -> set[int]:
    moving = set()
    for b in range(1, model.nbody):
        root = b
        while root:
            if model.body_jntnum[root] > 0 or model.body_mocapid[root] >= 0:
                moving.add(b)
                break
            root = model.body_parentid[root]
    return moving


class SceneMirror:
    """Keeps a viser scene (a server's or one client's) in step with ``model``/``data``."""

    def __init__(self, scene: viser.SceneApi, model: mujoco.MjModel, root: str = "/sim"):
        self.scene, self.model, self.root = scene, model, root
        self.handles: dict[int, viser.MeshHandle] = {}
        self.moving: list[int] = []
        moving_bodies = _moving_bodies(model)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        for g in range(model.ngeom):
            if model.geom_group[g] not in VISIBLE_GROUPS or geom_rgba(model, g)[3] < 0.05:
                continue
            mesh = geom_trimesh(model, g)
            if mesh is None:
                continue
            rgba = geom_rgba(model, g)
            handle = scene.add_mesh_simple(
                f"{root}/geom_{g}", mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32),
                color=tuple(int(255 * c) for c in rgba[:3]), opacity=float(rgba[3]) if rgba[3] < 1 else None,
                flat_shading=model.geom_type[g] != G.mjGEOM_MESH,
                position=data.geom_xpos[g], wxyz=self._quat(data, g),
            )
            self.handles[g] = handle
            if model.geom_bodyid[g] in moving_bodies:
                self.moving.append(g)

    @staticmethod
    def _quat(data: mujoco.MjData, g: int) -> np.ndarray:
        q = np.empty(4)
        mujoco.mju_mat2Quat(q, data.geom_xmat[g])
        return q

    def update(self, data: mujoco.MjData, server: viser.ViserServer | None = None) -> None:
        """Push the poses of every moving geom (in one atomic batch when a server is given)."""
        def push() -> None:
            for g in self.moving:
                h = self.handles[g]
                h.position = data.geom_xpos[g]
                h.wxyz = self._quat(data, g)

        if server is not None:
            with server.atomic():
                push()
        else:
            push()

    def set_static_pose(self, data: mujoco.MjData, geoms: list[int]) -> None:
        """Re-send poses of geoms moved by editing the model (e.g. target zones after a reset)."""
        for g in geoms:
            if g in self.handles:
                self.handles[g].position = data.geom_xpos[g]

    def remove(self) -> None:
        for h in self.handles.values():
            h.remove()
        self.handles.clear()
