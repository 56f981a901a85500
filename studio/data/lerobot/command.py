"""The LeRobot format's part of ``studio export lerobot`` / ``studio import lerobot``: its options and runs.

``studio.data.export_command`` / ``import_command`` own the commands (format choice, store opening) and call
these.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from studio.data.lerobot.reader import KINDS, read_lerobot, store_plan
from studio.data.lerobot.schema import VIDEO_CODEC, VIDEO_CRF, VIDEO_GOP, LeRobotError
from studio.data.lerobot.validate import validate_dataset
from studio.data.lerobot.writer import CODECS, export_lerobot
from studio.data.store import EpisodeStore, StoreError


def parse_task_map(items: Sequence[str] | None) -> dict[str, str]:
    """``--task-map`` items ('DATASET TASK=scene/task' pairs or JSON files) as one mapping."""
    out = {}
    for item in items or []:
        if item.endswith(".json") and Path(item).is_file():
            out.update(json.loads(Path(item).read_text()))
            continue
        if "=" not in item:
            raise LeRobotError(
                f"task map entries look like 'DATASET TASK=studio/task' or a JSON file, got {item!r}"
            )
        src, dst = item.rsplit("=", 1)
        out[src] = dst
    return out


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="new directory for the dataset")
    parser.add_argument("--tasks", nargs="+", default=None, help="only these tasks")
    parser.add_argument("--role", choices=("expert", "agent"), default=None, help="only this role")
    parser.add_argument("--embodiment", default=None, help="only this embodiment (sawyer, panda)")
    parser.add_argument("--source", nargs="+", default=None, help="only these sources")
    parser.add_argument(
        "--codec",
        choices=sorted(CODECS),
        default=VIDEO_CODEC,
        help="video encoder: libsvtav1 (AV1, LeRobot's default) or libx264 (H.264); "
        f"both with a keyframe every {VIDEO_GOP} frames and CRF {VIDEO_CRF}, as LeRobot encodes",
    )


def run_export(args: argparse.Namespace, store_of: Callable[[], EpisodeStore]) -> int:
    try:
        report = export_lerobot(
            store_of(),
            args.out,
            tasks=args.tasks,
            role=args.role,
            embodiment=args.embodiment,
            source=args.source,
            codec=args.codec,
        )
    except (LeRobotError, OSError) as e:
        print(f"studio export lerobot: {e}", file=sys.stderr)
        return 2
    problems = validate_dataset(args.out)
    print(report.summary() + f" to {args.out}")
    for p in problems:
        print(f"  schema problem: {p}", file=sys.stderr)
    return 1 if problems else 0


IMPORT_HELP = """\
A LeRobot v3.0 dataset imports as one of two kinds (--as auto picks the first that fits):

  trajectories    when it carries the studio's per-step features: observation.qpos,
                  observation.ee_pos_world, observation.ee_pos_cam, observation.gripper_opening,
                  observation.environment_state, osvi.gripper_cmd, osvi.time (a studio export has
                  them, and comes back exactly). Its camera stream gives the frames; without the
                  studio's camera columns the camera is a nominal one, flagged camera_nominal.
  demonstrations  any dataset with a camera stream, a video or an image feature (--camera picks
                  one): each episode's frames become an expert demonstration of the studio task
                  named by --task, as an uploaded human video does (thinned to 15 fps,
                  letterboxed to 240x320, a nominal camera, embodiment human unless --embodiment).

Tasks: the dataset's task strings name studio tasks when they are a studio task name or its
instruction ("pick up the bar and place it in the blue zone"); map others with --task-map.
Nothing is stored when anything is wrong. Episodes already imported (same content) are skipped
and listed.
"""


def add_import_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ((parser.description or "") + "\n\n" + IMPORT_HELP).strip()
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("dir", help="LeRobot v3.0 dataset directory")
    parser.add_argument(
        "--as",
        dest="kind",
        choices=KINDS,
        default="auto",
        help="import as trajectories or demonstration videos (default: trajectories when the studio's "
        "features are there)",
    )
    parser.add_argument(
        "--task", default=None, help="the studio task the episodes show (required for demonstration videos)"
    )
    parser.add_argument("--camera", default=None, help="the video or image feature to take frames from")
    parser.add_argument(
        "--episodes", nargs="+", type=int, default=None, metavar="N", help="only these episode indices"
    )
    parser.add_argument(
        "--task-map",
        nargs="+",
        default=None,
        metavar="MAP",
        help="'DATASET TASK=scene/task' pairs or a JSON file {dataset task: studio task}",
    )
    parser.add_argument(
        "--role", choices=("expert", "agent"), default=None, help="override the role of trajectories"
    )
    parser.add_argument(
        "--embodiment", default=None, help="override the embodiment (demonstrations: default human)"
    )


def run_import(args: argparse.Namespace, store_of: Callable[[], EpisodeStore]) -> int:
    """Read and check the dataset first; only then open (or create) the store and add the episodes."""
    from studio.sim.tasks import list_tasks

    try:
        plan = read_lerobot(
            args.dir,
            kind=args.kind,
            task=args.task,
            task_map=parse_task_map(args.task_map),
            role=args.role,
            embodiment=args.embodiment,
            known_tasks=list_tasks(),
            camera=args.camera,
            episodes=args.episodes,
        )
        store = store_of()
        metas, already = store_plan(store, plan)
    except (ValueError, OSError, StoreError) as e:  # LeRobotError and JSON errors are ValueErrors
        print(f"studio import lerobot: {e}", file=sys.stderr)
        return 2
    what = "trajectories" if plan.kind == "trajectories" else "demonstration videos"
    print(f"imported {len(metas)} episodes from {args.dir} as {what}")
    for m in metas:
        print(f"  {m.id}: {m.task}, {m.role}, {m.embodiment}, {m.num_frames} frames")
    if already:
        print(f"skipped {len(already)} episodes already in the store: {', '.join(already)}")
    return 0
