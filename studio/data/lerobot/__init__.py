"""LeRobot dataset v3.0 interop (being split into modules; everything lives in ``writer`` for now)."""

from studio.data.lerobot.writer import *  # noqa: F403
from studio.data.lerobot.writer import _parse_task_map  # noqa: F401
