"""The ``studio import FORMAT DIR`` command: bring trajectories from an ecosystem dataset (LeRobot v3.0) in."""

from __future__ import annotations

import argparse

from studio.data.export_command import add_format_arguments, open_checked_store
from studio.data.lerobot import command as lerobot_command


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_format_arguments(parser, lerobot_command.add_import_arguments)


def run(args: argparse.Namespace) -> int:
    return lerobot_command.run_import(args, open_checked_store(args.data_dir))
