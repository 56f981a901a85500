"""LeRobot dataset v3.0 interop: export the store's episodes, import trajectories back, validate the layout.

* :mod:`~studio.data.lerobot.schema` — the layout, path templates, features and ``LeRobotError``;
* :mod:`~studio.data.lerobot.writer` — ``export_lerobot`` and its ``ExportReport``;
* :mod:`~studio.data.lerobot.validate` — ``validate_dataset``;
* :mod:`~studio.data.lerobot.reader` — ``import_lerobot``;
* :mod:`~studio.data.lerobot.command` — the format's options and runs for ``studio export`` /
  ``studio import``.

The names other code uses are re-exported here.
"""

from studio.data.lerobot.command import add_export_arguments, add_import_arguments, run_export, run_import
from studio.data.lerobot.reader import import_lerobot
from studio.data.lerobot.schema import CODEBASE_VERSION, INFO_PATH, VIDEO_KEY, LeRobotError
from studio.data.lerobot.validate import validate_dataset
from studio.data.lerobot.writer import ExportReport, export_lerobot

__all__ = [
    "CODEBASE_VERSION",
    "INFO_PATH",
    "VIDEO_KEY",
    "ExportReport",
    "LeRobotError",
    "add_export_arguments",
    "add_import_arguments",
    "export_lerobot",
    "import_lerobot",
    "run_export",
    "run_import",
    "validate_dataset",
]
