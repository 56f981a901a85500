"""The ``studio import FORMAT DIR`` command: bring an ecosystem dataset's (LeRobot v3.0) episodes in, as trajectories
or as demonstration videos. The store is opened (and created) only once the dataset has been read and checked."""

from __future__ import annotations

import argparse

from studio.data.export_command import add_format_arguments, open_checked_store
from studio.data.lerobot import command as lerobot_command


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_format_arguments(parser, lerobot_command.add_import_arguments)


def run(args: argparse.Namespace) -> int:
    return lerobot_command.run_import(args, lambda: open_checked_store(args.data_dir))
