"""Scene families and their composition with a robot into one compiled MuJoCo model.

A scene file in ``scenes/`` holds the table, objects, target zones and the external camera; a robot
(:mod:`studio.sim.robots`) is composed with it at load time. Per-seed randomisation of where things
stand is a :class:`Layout`, sampled by the task (:mod:`studio.sim.tasks`) and applied by the
environment.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from studio.sim import robots

#: Folder of the MJCF scene files (``STUDIO_SCENES_DIR`` overrides, e.g. for an installed wheel).
SCENES_DIR = Path(os.environ.get("STUDIO_SCENES_DIR", Path(__file__).resolve().parents[2] / "scenes"))


@dataclass(frozen=True)
class SceneInfo:
    """A tabletop scene family.

    Attributes:
        name: ``"pick_place"`` or ``"push"``.
        objects: short names of the free objects (bodies and joints are ``obj_<name>``).
        targets: short names of the target zones (bodies ``target_<name>``), if any.
    """

    name: str
    objects: tuple[str, ...]
    targets: tuple[str, ...] = ()

    @property
    def xml_path(self) -> Path:
        return SCENES_DIR / f"{self.name}.xml"


SCENES: dict[str, SceneInfo] = {
    "pick_place": SceneInfo(
        "pick_place", objects=("cube", "cylinder", "prism", "bar"), targets=("red", "green", "blue", "yellow")
    ),
    "push": SceneInfo("push", objects=("red", "blue")),
}


def scene_info(name: str) -> SceneInfo:
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; choose from {sorted(SCENES)}") from None


@dataclass
class Layout:
    """Where the free objects and target zones stand after a reset.

    Attributes:
        object_pos: object name -> (x, y, z) of its body origin.
        object_yaw: object name -> rotation about world z, radians.
        target_pos: target name -> (x, y) centre of the zone.
    """

    object_pos: dict[str, np.ndarray] = field(default_factory=dict)
    object_yaw: dict[str, float] = field(default_factory=dict)
    target_pos: dict[str, np.ndarray] = field(default_factory=dict)


def compose_xml(scene: str, robot: str) -> str:
    """The MJCF text of ``scene`` with ``robot`` mounted at the world origin."""
    info = scene_info(scene)
    if not info.xml_path.exists():
        raise FileNotFoundError(f"scene file {info.xml_path} is missing (set STUDIO_SCENES_DIR?)")
    return f"""<mujoco model="{scene}-{robot}">
  <include file="{info.xml_path}"/>
  {robots.robot_xml(robot)}
  <compiler angle="radian" inertiafromgeom="auto" inertiagrouprange="0 5"/>
</mujoco>"""


def build_model(scene: str, robot: str) -> mujoco.MjModel:
    """Compile the scene with the robot: gravity compensation, grasp site and wrist camera included."""
    info = robots.robot_info(robot)
    spec = mujoco.MjSpec.from_string(compose_xml(scene, robot))
    robots.finish_spec(spec, info, scene)
    return spec.compile()


def build_robot_model(robot: str) -> mujoco.MjModel:
    """The robot alone (same mount), used by the IK solver so it never sees the objects' free joints."""
    info = robots.robot_info(robot)
    xml = f"""<mujoco model="{robot}-alone">{robots.robot_xml(robot)}
  <compiler angle="radian" inertiafromgeom="auto" inertiagrouprange="0 5"/></mujoco>"""
    spec = mujoco.MjSpec.from_string(xml)
    robots.finish_spec(spec, info)
    return spec.compile()
