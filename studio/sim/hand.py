"""A simulated human hand and forearm: the demonstrator of the Human-Franka tasks (robot name ``"hand"``).

The model is written here, not loaded from a package: a skin-coloured right hand — a palm of a box rounded by
capsules with a domed back, fingers and thumb of capsules with nails — and a forearm and sleeved upper arm behind
the wrist that rise up and back out of the external camera's view, so the hand reads as a person's arm reaching
in over the table.

* Motion: the hand body carries three slide joints (world x, y, z; its orientation is fixed, palm down, fingers
  forward) and is welded to a mocap body, moved with a bounded speed by :class:`HandMocap` exactly as the
  Sawyer's hand is. The slide joints are the "arm joints" a recording stores, so a stored hand episode replays.
* Fingers: three flexion hinges per digit (15), each with a position actuator. The gripper command curls them:
  0 is the relaxed open hand, 1 the pinch of thumb and index with the other three fingers curled towards the
  palm.
  The grasp site lies between the thumb and index fingertips of the pinch.
* Grasp: a scripted pinch (:class:`PinchGrasp`). When the gripper command rises above 0.5 with an object's
  centre within :data:`GRASP_RADIUS` of the grasp site, a weld from the hand to that object is switched on,
  keeping their relative pose of that moment; when the command falls below 0.5 it is switched off. The
  relative pose is kept in ``data.userdata`` and the switch is ``data.eq_active``, both part of MuJoCo's
  ``mjSTATE_INTEGRATION`` state, so a saved and restored state keeps the object in hand.
* Contacts: the hand touches nothing in the pick-and-place scene (a pinch needs no contact physics, and the
  approaching fingers do not knock objects about). In the scenes of :data:`CONTACT_SCENES` (push), where a
  person moves objects by touching them and never pinches them, one invisible box between the thumb and the
  fingertips (:data:`PUSHER_GEOM`) collides with the free objects: a push is made by the thumb or the
  fingertips at the height of the grasp site, and a box cannot slip in among the compliant finger joints.
  The hand never collides with the table.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

SKIN_RGBA = "0.87 0.68 0.55 1"
NAIL_RGBA = "0.93 0.78 0.72 1"
SLEEVE_RGBA = "0.22 0.32 0.48 1"

#: Scenes in which the hand pushes objects by contact.
CONTACT_SCENES = frozenset({"push"})
#: An object whose centre is this close to the grasp site when the pinch closes is picked up, metres.
GRASP_RADIUS = 0.035
#: Gripper commands above this close the pinch (and grasp), below it open it (and release).
PINCH_THRESHOLD = 0.5
#: Where the hand waits between episodes (grasp site, world frame), as the arms do.
HOME = np.array([0.0, 0.30, 0.25])

#: Names of the slide joints that move the hand.
ROOT_JOINTS = ("hand_x", "hand_y", "hand_z")
HAND_BODY = "hand"
MOCAP_BODY = "hand_mocap"
GRASP_SITE = "grasp_site"
PUSHER_GEOM = "hand_pusher"
INDEX_TIP_SITE = "hand_index_tip"
THUMB_TIP_SITE = "hand_thumb_tip"
WELD_PREFIX = "hand_grasp_"


@dataclass(frozen=True)
class Digit:
    """One finger or the thumb in the open pose.

    Attributes:
        name: ``thumb``, ``index``, ``middle``, ``ring`` or ``little``.
        points: base joint, the next two joints and the tip, in the hand frame (x to the person's right, y
            forward, z up, origin at the grasp site), metres.
        radii: capsule radius of each of the three segments.
        palmar: the direction the digit curls towards (the pad side), roughly.
        closed: flexion of each joint in the closed hand, radians.
    """

    name: str
    points: tuple[tuple[float, float, float], ...]
    radii: tuple[float, float, float]
    palmar: tuple[float, float, float]
    closed: tuple[float, float, float]


# The open hand hovers palm down over the grasp site: fingers reaching forward and down on the far side of it,
# the thumb down on the near side.
DIGITS = (
    Digit(
        "thumb",
        (
            (-0.0175, -0.070, 0.090),
            (-0.0235, -0.062, 0.048),
            (-0.0155, -0.058, 0.018),
            (-0.0035, -0.055, -0.005),
        ),
        (0.0115, 0.0105, 0.0095),
        (0.0, 1.0, 0.0),
        (0.22, 0.07, 0.06),
    ),
    Digit(
        "index",
        ((0.0025, -0.002, 0.074), (0.0025, 0.030, 0.047), (0.0025, 0.045, 0.027), (0.0025, 0.054, 0.010)),
        (0.0095, 0.0088, 0.0082),
        (0.0, -1.0, 0.0),
        (0.12, 0.31, 0.20),
    ),
    Digit(
        "middle",
        ((0.0235, 0.000, 0.077), (0.0235, 0.034, 0.048), (0.0235, 0.050, 0.026), (0.0235, 0.059, 0.007)),
        (0.0098, 0.0090, 0.0084),
        (0.0, -1.0, 0.0),
        (0.8, 1.2, 0.8),
    ),
    Digit(
        "ring",
        ((0.0435, -0.005, 0.075), (0.0445, 0.027, 0.048), (0.0445, 0.042, 0.028), (0.0445, 0.050, 0.011)),
        (0.0093, 0.0086, 0.0080),
        (0.0, -1.0, 0.0),
        (0.9, 1.3, 0.8),
    ),
    Digit(
        "little",
        ((0.0615, -0.014, 0.071), (0.0635, 0.011, 0.050), (0.0635, 0.023, 0.035), (0.0635, 0.030, 0.020)),
        (0.0084, 0.0078, 0.0072),
        (0.0, -1.0, 0.0),
        (1.0, 1.35, 0.8),
    ),
)

#: The wrist (where the forearm starts) and the direction the forearm leaves it: up and back.
WRIST = np.array([0.0285, -0.088, 0.118])
FOREARM_DIR = np.array([0.0, -0.72, 0.69])
FOREARM_LEN = 0.27
UPPER_ARM_DIR = np.array([0.0, -0.35, 0.94])
UPPER_ARM_LEN = 0.35

FINGER_JOINTS = tuple(f"hand_{d.name}{i}" for d in DIGITS for i in (1, 2, 3))
FINGER_ACTUATORS = FINGER_JOINTS
#: Joint targets of the closed hand, in the order of :data:`FINGER_JOINTS` (the open hand is all zeros).
CLOSED_POSE = np.array([a for d in DIGITS for a in d.closed])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _frame(z, hint) -> np.ndarray:
    """Rotation whose z axis is ``z`` and whose x axis is the flexion axis curling z towards ``hint``."""
    z = _unit(z)
    p = np.asarray(hint, dtype=np.float64)
    p = p - (p @ z) * z
    x = _unit(np.cross(z, p))  # rotating about x by a positive angle turns z towards p
    return np.column_stack([x, np.cross(z, x), z])


def _quat(R: np.ndarray) -> str:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return " ".join(f"{v:.6f}" for v in q)


def _vec(v) -> str:
    return " ".join(f"{float(x):.5f}" for x in v)


def _digit_xml(d: Digit) -> str:
    pts = [np.asarray(p, dtype=np.float64) for p in d.points]
    frames = [_frame(pts[i + 1] - pts[i], d.palmar) for i in range(3)]
    out: list[str] = []
    close: list[str] = []
    parent_pos, parent_R = np.zeros(3), np.eye(3)
    for i in range(3):
        length = float(np.linalg.norm(pts[i + 1] - pts[i]))
        rel_pos = parent_R.T @ (pts[i] - parent_pos)
        rel_R = parent_R.T @ frames[i]
        name = f"hand_{d.name}{i + 1}"
        upper = 1.7 if d.name != "thumb" else 1.2
        lines = [
            f'<body name="{name}" pos="{_vec(rel_pos)}" quat="{_quat(rel_R)}">',
            f'  <joint name="{name}" class="hand_finger" range="-0.2 {upper}"/>',
            f'  <geom name="{name}" class="hand_skin" type="capsule" size="{d.radii[i]:.4f}" '
            f'fromto="0 0 0 0 0 {length:.5f}"/>',
        ]
        if i == 2:
            # A nail on the back of the last segment, and the fingertip point.
            lines.append(
                f'  <geom name="{name}_nail" class="hand_visual" type="ellipsoid" rgba="{NAIL_RGBA}" '
                f'size="{0.75 * d.radii[i]:.4f} {0.35 * d.radii[i]:.4f} {0.9 * d.radii[i]:.4f}" '
                f'pos="0 {0.72 * d.radii[i]:.4f} {length - 0.6 * d.radii[i]:.4f}"/>'
            )
            tip = INDEX_TIP_SITE if d.name == "index" else THUMB_TIP_SITE if d.name == "thumb" else None
            if tip:
                lines.append(f'  <site name="{tip}" pos="0 0 {length:.5f}" size="0.004"/>')
        out.extend("  " * i + line for line in lines)
        close.append("  " * i + "</body>")
        parent_pos, parent_R = pts[i], frames[i]
    return "\n".join(out + close[::-1])


def _palm_xml() -> str:
    """Palm (a box rounded by capsules on its four edges and a domed back, the thenar pad at the thumb), wrist,
    forearm and arm."""
    mcps = [np.asarray(d.points[0], dtype=np.float64) for d in DIGITS[1:]]
    knuckles = np.mean(mcps, axis=0)
    length = _unit(knuckles - WRIST)
    lateral = _unit(np.array([1.0, 0.0, 0.0]) - length[0] * length)
    dorsal = np.cross(lateral, length)  # up and forward: the back of the hand
    R = np.column_stack([lateral, dorsal, -length])

    def at(lat: float, along: float, up: float = 0.0) -> np.ndarray:
        return WRIST + lat * lateral + along * length + up * dorsal

    span = float((knuckles - WRIST) @ length)
    radial = float((mcps[0] - WRIST) @ lateral) - 0.002
    ulnar = float((mcps[-1] - WRIST) @ lateral) + 0.002
    knuckle_line = f"{_vec(mcps[0] - 0.004 * length)} {_vec(mcps[-1] - 0.004 * length)}"
    box_c = at(0.5 * (radial + ulnar), 0.5 * (0.012 + span - 0.006), -0.002)
    thumb0, thumb1 = (np.asarray(p, dtype=np.float64) for p in DIGITS[0].points[:2])
    thenar_c = 0.55 * thumb0 + 0.45 * thumb1 + 0.010 * lateral - 0.004 * dorsal + 0.006 * length
    f_end = WRIST + FOREARM_LEN * _unit(FOREARM_DIR)
    u_end = f_end + UPPER_ARM_LEN * _unit(UPPER_ARM_DIR)
    sleeve_start = WRIST + 0.17 * _unit(FOREARM_DIR)
    return f"""
      <geom name="hand_palm" class="hand_skin" type="box" pos="{_vec(box_c)}" quat="{_quat(R)}"
            size="{0.5 * (ulnar - radial):.4f} 0.0095 {0.5 * (span - 0.018):.4f}"/>
      <geom name="hand_dorsum" class="hand_skin" type="ellipsoid" pos="{_vec(box_c + 0.001 * dorsal)}"
            quat="{_quat(R)}" size="{0.5 * (ulnar - radial) + 0.003:.4f} 0.0125 {0.5 * span - 0.002:.4f}"/>
      <geom name="hand_knuckles" class="hand_skin" type="capsule" size="0.0125" fromto="{knuckle_line}"/>
      <geom name="hand_palm_radial" class="hand_skin" type="capsule" size="0.012"
            fromto="{_vec(at(radial + 0.004, 0.014))} {_vec(mcps[0] - 0.004 * length)}"/>
      <geom name="hand_palm_ulnar" class="hand_skin" type="capsule" size="0.0125"
            fromto="{_vec(at(ulnar - 0.004, 0.014))} {_vec(mcps[-1] - 0.004 * length)}"/>
      <geom name="hand_palm_heel" class="hand_skin" type="capsule" size="0.0125"
            fromto="{_vec(at(radial + 0.006, 0.016))} {_vec(at(ulnar - 0.006, 0.016))}"/>
      <geom name="hand_thenar" class="hand_skin" type="ellipsoid" size="0.016 0.013 0.027"
            pos="{_vec(thenar_c)}" quat="{_quat(_frame(thumb1 - thumb0, (0, 1, 0)))}"/>
      <geom name="hand_wrist" class="hand_visual" type="ellipsoid" size="0.031 0.021 0.024" pos="{_vec(WRIST)}"
            quat="{_quat(R)}"/>
      <geom name="hand_forearm" class="hand_visual" type="capsule" size="0.026"
            fromto="{_vec(WRIST)} {_vec(WRIST + 0.5 * (f_end - WRIST))}"/>
      <geom name="hand_forearm2" class="hand_visual" type="capsule" size="0.031"
            fromto="{_vec(WRIST + 0.45 * (f_end - WRIST))} {_vec(f_end)}"/>
      <geom name="hand_sleeve" class="hand_visual" type="capsule" size="0.040" rgba="{SLEEVE_RGBA}"
            fromto="{_vec(sleeve_start)} {_vec(f_end)}"/>
      <geom name="hand_upper_arm" class="hand_visual" type="capsule" size="0.045" rgba="{SLEEVE_RGBA}"
            fromto="{_vec(f_end)} {_vec(u_end)}"/>"""


def hand_xml() -> str:
    """The MJCF fragment (defaults, worldbody, actuators, equality) of the hand with its forearm."""
    digits = "\n".join(_digit_xml(d) for d in DIGITS)
    actuators = "\n".join(
        f'    <position name="{j}" joint="{j}" class="hand_finger"/>' for j in FINGER_ACTUATORS
    )
    return f"""
  <default>
    <default class="hand_skin">
      <geom rgba="{SKIN_RGBA}" contype="0" conaffinity="0" density="1000" condim="3" friction="0.8 0.01 0.001"/>
    </default>
    <default class="hand_visual">
      <geom rgba="{SKIN_RGBA}" contype="0" conaffinity="0" density="300"/>
    </default>
    <default class="hand_finger">
      <joint type="hinge" axis="1 0 0" damping="0.02" armature="0.0005" limited="true"/>
      <position kp="2" ctrlrange="-0.2 1.7" forcerange="-3 3"/>
    </default>
  </default>
  <worldbody>
    <body name="{MOCAP_BODY}" mocap="true" pos="{_vec(HOME)}"/>
    <body name="{HAND_BODY}" pos="0 0 0">
      <joint name="hand_x" type="slide" axis="1 0 0" damping="1"/>
      <joint name="hand_y" type="slide" axis="0 1 0" damping="1"/>
      <joint name="hand_z" type="slide" axis="0 0 1" damping="1"/>
      <site name="{GRASP_SITE}" pos="0 0 0" size="0.006"/>
      <!-- What touches objects in a contact scene: the volume between thumb and fingertips, not the capsules. -->
      <geom name="{PUSHER_GEOM}" type="box" size="0.03 0.04 0.02" pos="0 0 0.005" group="3" rgba="0.9 0.2 0.9 0.3"
            contype="0" conaffinity="0" mass="0.001" condim="3" friction="0.8 0.01 0.001"/>
      <camera name="wrist" pos="0.0 -0.035 0.075" xyaxes="1 0 0 0 1 0" fovy="75"/>
{_palm_xml()}
{digits}
    </body>
  </worldbody>
  <actuator>
{actuators}
  </actuator>
  <equality>
    <weld name="hand_weld" body1="{MOCAP_BODY}" body2="{HAND_BODY}" relpose="0 0 0 1 0 0 0" solref="0.01 1"/>
  </equality>
"""


def object_bodies(spec: mujoco.MjSpec) -> list[str]:
    """Names of the scene's free objects (bodies ``obj_<name>``, the scenes' convention)."""
    return [b.name for b in spec.bodies if b.name.startswith("obj_")]


def finish_spec(spec: mujoco.MjSpec, scene: str | None) -> None:
    """Edits the composed spec for ``scene`` (None: the hand alone). In the scenes of :data:`CONTACT_SCENES` the
    hand's contact proxy meets the free objects; elsewhere every free object gets an (inactive) grasp weld, and
    the model the user data the pinch keeps its state in."""
    objects = object_bodies(spec)
    if scene in CONTACT_SCENES:
        # The proxy (contype 2) meets objects (conaffinity gains bit 2), never the table (contype/conaffinity 1).
        spec.geom(PUSHER_GEOM).contype = 2
        for body in objects:
            for geom in spec.body(body).geoms:
                geom.conaffinity |= 2
        objects = []
    for body in objects:
        spec.add_equality(
            name=WELD_PREFIX + body.removeprefix("obj_"),
            type=mujoco.mjtEq.mjEQ_WELD,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1=HAND_BODY,
            name2=body,
            active=False,
            # anchor, relative position, relative orientation, torque scale; set when the pinch closes.
            data=[0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1],
            solref=[0.01, 1.0],
        )
    spec.nuserdata = max(spec.nuserdata, PinchGrasp.userdata_size(len(objects)))


class PinchGrasp:
    """The scripted pinch: grasps by switching on a weld between the hand and an object, releases by switching
    it off. Its state lives in ``data`` (``eq_active`` and ``userdata``), so it survives a saved and restored
    physics state; :meth:`refresh` re-applies a restored grasp's relative pose to the model.

    ``data.userdata`` holds the last gripper command, then per object its position and orientation (w, x, y, z)
    in the hand frame at the moment it was grasped.
    """

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.root_qadr = np.array([model.jnt_qposadr[model.joint(j).id] for j in ROOT_JOINTS])
        self.objects: list[str] = []
        self.eq_ids: list[int] = []
        self.obj_qadr: list[int] = []
        for i in range(model.neq):
            name = model.equality(i).name
            if name.startswith(WELD_PREFIX):
                obj = name.removeprefix(WELD_PREFIX)
                self.objects.append(obj)
                self.eq_ids.append(i)
                self.obj_qadr.append(int(model.jnt_qposadr[model.joint(f"obj_{obj}").id]))
        if model.nuserdata < self.userdata_size(len(self.objects)):
            raise ValueError(
                "the model lacks the user data of the hand's pinch (built without hand.finish_spec?)"
            )

    @staticmethod
    def userdata_size(n_objects: int) -> int:
        return 1 + 7 * n_objects

    def grasp_point(self, data: mujoco.MjData) -> np.ndarray:
        """The grasp site in the world: the hand body's origin, which only translates (its slide joints)."""
        return data.qpos[self.root_qadr].copy()

    def held(self, data: mujoco.MjData) -> str | None:
        """The object welded to the hand, if any."""
        for obj, eq in zip(self.objects, self.eq_ids, strict=True):
            if data.eq_active[eq]:
                return obj
        return None

    def update(self, data: mujoco.MjData, gripper: float) -> None:
        """Apply a gripper command before a physics step: grasp on closing, release on opening."""
        closing = gripper >= PINCH_THRESHOLD and data.userdata[0] < PINCH_THRESHOLD
        data.userdata[0] = gripper
        if gripper < PINCH_THRESHOLD:
            data.eq_active[self.eq_ids] = 0
        elif closing and self.held(data) is None:
            self._grasp_nearest(data)
        self.refresh(data)

    def _grasp_nearest(self, data: mujoco.MjData) -> None:
        point = self.grasp_point(data)
        dists = [float(np.linalg.norm(data.qpos[a : a + 3] - point)) for a in self.obj_qadr]
        if not dists or min(dists) > GRASP_RADIUS:
            return
        k = int(np.argmin(dists))
        a = self.obj_qadr[k]
        # The hand frame is the world frame translated to the grasp site: the object's pose relative to it is
        # its world pose shifted by the grasp point.
        data.userdata[1 + 7 * k : 4 + 7 * k] = data.qpos[a : a + 3] - point
        data.userdata[4 + 7 * k : 8 + 7 * k] = data.qpos[a + 3 : a + 7]
        data.eq_active[self.eq_ids[k]] = 1

    def refresh(self, data: mujoco.MjData) -> None:
        """Copy the held object's relative pose from ``data.userdata`` into the model's weld."""
        for k, eq in enumerate(self.eq_ids):
            if data.eq_active[eq]:
                self.model.eq_data[eq, 3:10] = data.userdata[1 + 7 * k : 8 + 7 * k]
