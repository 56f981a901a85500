"""Click-to-reach teleop: where a click in the 3D view sends the gripper, and the smooth path it takes there.

A person without a 3D mouse points at things. A click casts the browser's ray into the scene as the tab draws
it (the session's :class:`~studio.backend.messages.SceneGeometry` at the latest body poses); the gripper then
moves over the hit point *at its current height*, so a click never drives the fingers into what lies between.
Height is a separate choice: **Down** descends to the grasp height of the object under the gripper (its centre,
never below the robot's lowest grasp height — the scripted experts' rule), to the place height of an object the
gripper holds (where it rested, plus a centimetre), or to just above the table; **Up** lifts to the experts'
carrying height. Nudges move by a fixed step along one axis.

Every motion is a stream of ordinary end-effector targets along a minimum-jerk path, so the sim worker's IK and
the recording see exactly what a gizmo drag would produce: the person chooses where, nothing is scripted.
Robot bodies are never hit (a click on the arm is not a place to go); an *object* is a small movable-looking
body (not the robot, the table, a wall or a flat zone marker).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
import viser.transforms as vtf

from studio.backend import messages as msg
from studio.sim.experts import LIFT_Z
from studio.sim.robots import robot_info
from studio.sim.waypoints import ControllerConfig

#: Path speed of a click's motion (metres per second); the shortest motion still takes MIN_DURATION_S.
REACH_SPEED = 0.3
MIN_DURATION_S = 0.4
#: Targets per second while a path runs (the session applies the newest one at each 100 Hz tick).
PATH_HZ = 50.0
#: Above an object's rest height, a held object is set down this much higher (the experts' place height).
PLACE_CLEARANCE = 0.01
#: Lowest grasp-site height over a surface that is not an object (fingertips just off the table).
TABLE_CLEARANCE = 0.035
#: An object counts as "under the gripper" within this horizontal distance of the grasp point, and as held when
#: the gripper is closed and its centre is within HOLD_RADIUS of the grasp point.
UNDER_RADIUS = 0.05
HOLD_RADIUS = 0.05
#: Bodies wider than this (metres) are surfaces (table, walls), not objects; thinner than MIN_OBJECT_HEIGHT are
#: flat markers (target zones).
MAX_OBJECT_SIZE = 0.25
MIN_OBJECT_HEIGHT = 0.01
#: Nudge steps offered in the panel, metres.
NUDGE_STEPS = {"5 mm": 0.005, "1 cm": 0.01, "2 cm": 0.02, "5 cm": 0.05}
#: The workspace a target is kept in (metres, world frame): above the table, within the arms' reach.
WORKSPACE_LOW = np.array([-0.6, -0.1, 0.0])
WORKSPACE_HIGH = np.array([0.6, 1.1, 0.6])
_IGNORED_BODIES = ("world", "mocap")


@dataclass(frozen=True)
class Hit:
    """Where a ray met the scene: the world point, the body's name and whether that body is an object."""

    point: np.ndarray
    body: str
    is_object: bool


def body_transform(poses: np.ndarray, body: int) -> np.ndarray:
    """4×4 world pose of body row ``body`` of a (B, 7) xyz + wxyz pose array."""
    T = np.eye(4)
    T[:3, :3] = vtf.SO3(np.asarray(poses[body, 3:7], dtype=np.float64)).as_matrix()
    T[:3, 3] = poses[body, :3]
    return T


def geom_transform(geom: msg.GeomSpec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = vtf.SO3(np.asarray(geom.quat, dtype=np.float64)).as_matrix()
    T[:3, 3] = geom.pos
    return T


@dataclass
class SceneModel:
    """The clickable scene of one session: the visible geoms of every non-robot body, as the tab draws them."""

    geometry: msg.SceneGeometry
    robot: str
    _triangles: dict[int, np.ndarray] = field(default_factory=dict)
    objects: frozenset[str] = frozenset()
    #: Each object's bounding box in its body frame: (centre, size).
    boxes: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from studio.ui.scene_view import MAX_FACES, geom_mesh

        prefixes = robot_info(self.robot).body_prefix
        names = self.geometry.body_names
        extents: dict[int, list[np.ndarray]] = {}
        for i, g in enumerate(self.geometry.geoms):
            name = names[g.body]
            if g.rgba[3] < 0.05 or name in _IGNORED_BODIES or name.startswith(prefixes):
                continue
            mesh = geom_mesh(g, self.geometry.meshes, MAX_FACES)
            if mesh is None or not len(mesh.faces):
                continue
            self._triangles[i] = np.asarray(mesh.triangles, dtype=np.float64)
            corners = trimesh.transform_points(trimesh.bounds.corners(mesh.bounds), geom_transform(g))
            extents.setdefault(g.body, []).extend(corners)
        for body, pts in extents.items():
            lo, hi = np.min(pts, axis=0), np.max(pts, axis=0)
            size = hi - lo
            if max(size[0], size[1]) <= MAX_OBJECT_SIZE and size[2] >= MIN_OBJECT_HEIGHT:
                self.boxes[names[body]] = ((lo + hi) / 2, size)
        self.objects = frozenset(self.boxes)

    def cast(self, poses: np.ndarray, origin, direction, skip: frozenset[str] = frozenset()) -> Hit | None:
        """The nearest visible non-robot surface along the ray (None: the ray hits nothing)."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        best: tuple[float, np.ndarray, int] | None = None
        names = self.geometry.body_names
        for i, triangles in self._triangles.items():
            g = self.geometry.geoms[i]
            if names[g.body] in skip or g.body >= len(poses):
                continue
            T = body_transform(poses, g.body) @ geom_transform(g)
            inv = np.linalg.inv(T)
            lo = inv[:3, :3] @ o + inv[:3, 3]
            ld = inv[:3, :3] @ d
            s = ray_triangles(lo, ld, triangles)
            if np.isfinite(s):
                world = T[:3, :3] @ (lo + s * ld) + T[:3, 3]
                t = float(np.dot(world - o, d))
                if t > 1e-6 and (best is None or t < best[0]):
                    best = (t, world, g.body)
        if best is None:
            return None
        name = names[best[2]]
        return Hit(point=best[1], body=name, is_object=name in self.objects)

    def outline(self, poses: np.ndarray, body: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World centre, orientation (wxyz) and size of object ``body``'s bounding box."""
        index = self.geometry.body_names.index(body)
        centre, size = self.boxes[body]
        T = body_transform(poses, index)
        return T[:3, :3] @ centre + T[:3, 3], np.asarray(poses[index, 3:7], dtype=np.float64), size

    def object_positions(self, poses: np.ndarray) -> dict[str, np.ndarray]:
        """World position of every object body."""
        index = {n: i for i, n in enumerate(self.geometry.body_names)}
        return {
            n: np.asarray(poses[index[n], :3], dtype=np.float64)
            for n in self.objects
            if index[n] < len(poses)
        }


def ray_triangles(origin: np.ndarray, direction: np.ndarray, triangles: np.ndarray) -> float:
    """The smallest positive ray parameter at which the ray meets one of ``triangles`` ((F, 3, 3)); inf: none.

    Möller–Trumbore, vectorised over the triangles (both faces count: a click may come from any side)."""
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = origin - v0
    u = np.einsum("ij,ij->i", tv, p) * inv
    q = np.cross(tv, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    return float(t[hit].min()) if hit.any() else float("inf")


def clip_to_workspace(p: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(p, dtype=np.float64), WORKSPACE_LOW, WORKSPACE_HIGH)


@dataclass
class HeightRules:
    """How Down and Up choose a height for one robot; remembers where objects rested (their place height)."""

    robot: str
    rest_z: dict[str, float] = field(default_factory=dict)

    @property
    def lowest(self) -> float:
        return float(ControllerConfig().min_grasp_z.get(self.robot, 0.03))

    def remember_rest(self, objects: dict[str, np.ndarray], ee: np.ndarray | None = None) -> None:
        """Record where objects rest (the poses of a freshly reset or restored scene); an object at the grasp
        point ``ee`` may be held (a restored fork), so its rest height stays unknown."""
        self.rest_z = {
            n: float(p[2])
            for n, p in objects.items()
            if ee is None or float(np.linalg.norm(p - np.asarray(ee))) > HOLD_RADIUS
        }

    def held(self, ee: np.ndarray, gripper: float, objects: dict[str, np.ndarray]) -> str | None:
        """The object the closed gripper holds (its centre within HOLD_RADIUS of the grasp point), if any."""
        if gripper < 0.5:
            return None
        near = [(float(np.linalg.norm(p - ee)), n) for n, p in objects.items()]
        near = [x for x in near if x[0] <= HOLD_RADIUS]
        return min(near)[1] if near else None

    def under(self, ee: np.ndarray, objects: dict[str, np.ndarray], skip: str | None = None) -> str | None:
        """The object nearest below the grasp point horizontally (within UNDER_RADIUS), if any."""
        near = [
            (float(np.linalg.norm(p[:2] - ee[:2])), n)
            for n, p in objects.items()
            if n != skip and p[2] < ee[2] + 0.02
        ]
        near = [x for x in near if x[0] <= UNDER_RADIUS]
        return min(near)[1] if near else None

    def down(
        self, ee: np.ndarray, gripper: float, objects: dict[str, np.ndarray], surface_z: float | None
    ) -> tuple[float, str]:
        """The height Down goes to, and why (for the status line)."""
        holding = self.held(ee, gripper, objects)
        if holding is not None:
            rest = self.rest_z.get(holding, float(objects[holding][2]))
            # where the grasp point is when the object rests: the object may sit lower or higher in the fingers
            # than it was grasped (it slips), and aiming the grasp point at the rest height would then press it
            # into the table and never arrive
            offset = float(ee[2]) - float(objects[holding][2])
            return max(rest + offset, self.lowest) + PLACE_CLEARANCE, f"placing the {object_label(holding)}"
        below = self.under(ee, objects)
        if below is not None:
            return max(float(objects[below][2]), self.lowest), f"to grasp height of the {object_label(below)}"
        base = 0.0 if surface_z is None else surface_z
        return max(base + TABLE_CLEARANCE, self.lowest), "just above the table"

    def up(self, ee: np.ndarray) -> float:
        return max(LIFT_Z, float(ee[2]))


def down_height(
    model: SceneModel, rules: HeightRules, poses: np.ndarray, ee: np.ndarray, gripper: float
) -> tuple[float, str]:
    """Where Down sends the grasp point from ``ee`` (with the gripper command ``gripper``), and why."""
    objects = model.object_positions(poses)
    held = rules.held(ee, gripper, objects)
    below = model.cast(poses, ee, (0.0, 0.0, -1.0), skip=frozenset({held} if held else ()))
    return rules.down(ee, gripper, objects, None if below is None else float(below.point[2]))


def object_label(body: str) -> str:
    """How the status line names a body (``obj_cube`` → ``cube``, ``target_red`` → ``red zone``)."""
    if body.startswith("obj_"):
        return body[4:]
    if body.startswith("target_"):
        return f"{body[7:]} zone"
    return body


def min_jerk(start: np.ndarray, goal: np.ndarray, s: float) -> np.ndarray:
    """The minimum-jerk interpolation between ``start`` and ``goal`` at phase ``s`` in [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    return start + (goal - start) * blend


def path_duration(start: np.ndarray, goal: np.ndarray) -> float:
    return max(MIN_DURATION_S, float(np.linalg.norm(goal - start)) / REACH_SPEED)


def path_targets(start: np.ndarray, goal: np.ndarray, hz: float = PATH_HZ) -> np.ndarray:
    """The targets a path sends, one per 1/hz seconds, ending exactly at ``goal``."""
    n = max(1, int(np.ceil(path_duration(start, goal) * hz)))
    return np.array([min_jerk(start, goal, k / n) for k in range(1, n + 1)])
