"""Where the dataset lives: the root directory and the fixed layout of the store inside it.

The root is chosen, in order of precedence, by the ``--data-dir`` option, the ``STUDIO_DATA_DIR``
environment variable, or the user's data directory (``platformdirs``, e.g. ``~/.local/share/osvi-studio``
on Linux). Inside it::

    catalog.sqlite            the SQLite (WAL) catalog of episodes, tasks, runs, checkpoints and rollouts
    episodes/<id>/            one directory per stored episode (see :mod:`studio.data.episode`)
    tmp/                      episodes being written (and their lock files); leftovers are cleaned at start-up
    cache/frames/<H>x<W>/     decoded frames at a training resolution (see :mod:`studio.data.training_view`)

Trained policies shipped with the package live outside it, in ``SHIPPED_POLICY_DIR`` (``studio/policies``).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import platformdirs

ENV_VAR = "STUDIO_DATA_DIR"
APP_NAME = "osvi-studio"

CATALOG_NAME = "catalog.sqlite"
EPISODES_DIR = "episodes"
TMP_DIR = "tmp"
CACHE_DIR = "cache"

#: Policy files installed with the package (``NAME.pt``, its latent decoder ``NAME.decoder.pt``).
SHIPPED_POLICY_DIR = Path(__file__).resolve().parents[1] / "policies"
#: The catalog's run and name for them.
SHIPPED_RUN_ID, SHIPPED_RUN_NAME = "shipped", "policies shipped with the studio"


def default_data_dir() -> Path:
    """The dataset root used when neither ``--data-dir`` nor ``STUDIO_DATA_DIR`` is given."""
    return platformdirs.user_data_path(APP_NAME) / "data"


def resolve_data_dir(cli_value: str | os.PathLike | None = None) -> Path:
    """The dataset root: the explicit value if given, else the environment variable, else the default."""
    if cli_value:
        return Path(cli_value).expanduser().resolve()
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser().resolve()
    return default_data_dir()


def add_data_dir_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--data-dir`` option every data command shares."""
    parser.add_argument(
        "--data-dir",
        default=None,
        help=f"dataset root (default: ${ENV_VAR} or {default_data_dir()})",
    )
