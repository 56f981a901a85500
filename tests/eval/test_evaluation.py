"""`studio eval` on the command line: task names give their scene, and bad task lists are a clear error."""

from __future__ import annotations

import argparse

from studio.eval.evaluation import add_arguments, run


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(["--checkpoint", "oracle", *argv])


def test_tasks_of_two_scenes_are_refused_before_anything_runs(capsys, tmp_path):
    assert run(_args("--tasks", "pick_place/cube->red,push/red-forward", "--data-dir", str(tmp_path))) == 2
    assert "belongs to scene 'push', not 'pick_place'" in capsys.readouterr().err


def test_an_unknown_task_is_refused(capsys, tmp_path):
    assert run(_args("--tasks", "push/green-forward", "--data-dir", str(tmp_path))) == 2
    assert "unknown task 'push/green-forward' for scene 'push'" in capsys.readouterr().err
