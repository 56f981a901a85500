"""The ``studio import FORMAT DIR`` command: bring trajectories from an ecosystem dataset (LeRobot v3.0) in."""

from __future__ import annotations

import argparse
import sys

from studio.data import lerobot
from studio.data.paths import add_data_dir_argument
from studio.data.store import EpisodeStore

FORMATS = ("lerobot",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=FORMATS, help="dataset format")
    lerobot.add_import_arguments(parser)
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    store = EpisodeStore(args.data_dir)
    report = store.check()
    if not report.ok:
        print(report.summary(), file=sys.stderr)
    return lerobot.run_import(args, store)
