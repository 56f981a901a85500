"""What a remote viewer needs from a running simulation: body poses each tick and the visual geometry once.

Rows are MuJoCo body ids (row 0 is the world), so :class:`~studio.backend.messages.PoseFrame` rows
and :class:`~studio.backend.messages.GeomSpec` ``body`` indices agree without a lookup table.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Literal

import mujoco
import numpy as np

from studio.backend import messages as msg

#: The values of :attr:`studio.backend.messages.GeomSpec.type`.
GeomType = Literal["plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh", "sdf"]

_GEOM_TYPES: dict[int, GeomType] = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane",
    int(mujoco.mjtGeom.mjGEOM_HFIELD): "hfield",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_MESH): "mesh",
    int(mujoco.mjtGeom.mjGEOM_SDF): "sdf",
}


def _vec3(values: Iterable[float]) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z


def _vec4(values: Iterable[float]) -> tuple[float, float, float, float]:
    a, b, c, d = (float(v) for v in values)
    return a, b, c, d


def body_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """Name of every body by id (``body<i>`` for unnamed ones)."""
    return tuple(model.body(i).name or f"body{i}" for i in range(model.nbody))


def body_poses(data: mujoco.MjData) -> np.ndarray:
    """(nbody, 7) float32: world position and quaternion (w, x, y, z) of every body."""
    return np.hstack([data.xpos, data.xquat]).astype(np.float32)


def pose_frame(
    data: mujoco.MjData, *, seq: int, step: int, ack_seq: int, ee_pos: np.ndarray, gripper: float
) -> msg.PoseFrame:
    return msg.PoseFrame.pack(
        body_poses(data),
        seq=seq,
        step=step,
        sim_time=float(data.time),
        ack_seq=ack_seq,
        ee_pos=tuple(float(v) for v in ee_pos),
        gripper=min(1.0, max(0.0, float(gripper))),
    )


def scene_geometry(model: mujoco.MjModel, max_group: int = 2) -> msg.SceneGeometry:
    """Visual geoms (group ≤ ``max_group``; the studio's collision-only geoms sit in group 3) and meshes."""
    meshes: list[msg.MeshSpec] = []
    mesh_index: dict[int, int] = {}
    geoms: list[msg.GeomSpec] = []
    for g in range(model.ngeom):
        gtype = _GEOM_TYPES.get(int(model.geom_type[g]))
        if gtype is None or int(model.geom_group[g]) > max_group:
            continue
        mesh = -1
        if gtype == "mesh":
            mid = int(model.geom_dataid[g])
            if mid not in mesh_index:
                va, vn = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
                fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
                mesh_index[mid] = len(meshes)
                meshes.append(
                    msg.MeshSpec(
                        name=model.mesh(mid).name or f"mesh{mid}",
                        vertices=np.ascontiguousarray(model.mesh_vert[va : va + vn], dtype="<f4").tobytes(),
                        faces=np.ascontiguousarray(model.mesh_face[fa : fa + fn], dtype="<i4").tobytes(),
                    )
                )
            mesh = mesh_index[mid]
        matid = int(model.geom_matid[g])
        rgba = model.mat_rgba[matid] if matid >= 0 else model.geom_rgba[g]
        geoms.append(
            msg.GeomSpec(
                body=int(model.geom_bodyid[g]),
                type=gtype,
                group=int(model.geom_group[g]),
                size=_vec3(model.geom_size[g]),
                pos=_vec3(model.geom_pos[g]),
                quat=_vec4(model.geom_quat[g]),
                rgba=_vec4(rgba),
                mesh=mesh,
            )
        )
    return msg.SceneGeometry(body_names=body_names(model), geoms=tuple(geoms), meshes=tuple(meshes))
