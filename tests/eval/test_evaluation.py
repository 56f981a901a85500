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


def test_an_unknown_expert_embodiment_is_refused(capsys, tmp_path):
    argv = ("--tasks", "pick_place/cube->red", "--data-dir", str(tmp_path), "--expert-embodiment", "robot")
    assert run(_args(*argv)) == 2
    assert "unknown embodiment(s) robot" in capsys.readouterr().err


def test_expert_embodiments_choose_the_demonstrations(tmp_path):
    import sys
    from pathlib import Path

    import pytest

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.store import EpisodeStore
    from studio.eval.evaluation import _expert_choices, expert_embodiments_of

    assert expert_embodiments_of(_args("--expert-embodiment", "human")) == ["human"]
    assert expert_embodiments_of(
        _args("--expert-embodiment", "human,panda", "--expert-embodiment", "sawyer")
    ) == [
        "human",
        "panda",
        "sawyer",
    ]
    assert expert_embodiments_of(_args()) is None
    task = "pick_place/cube->red"
    with EpisodeStore(tmp_path) as store:
        ids = {}
        for i, robot in enumerate(("sawyer", "hand", "panda")):
            ids[robot] = store.add_episode(
                make_recording(robot=robot, seed=i), role="expert", source="scripted"
            ).id
        store.add_episode(make_recording(robot="panda", seed=9), role="agent", source="scripted")
        assert _expert_choices(store, task) == sorted([ids["sawyer"], ids["hand"]])  # another embodiment's
        assert _expert_choices(store, task, ("human",)) == [ids["hand"]]
        assert _expert_choices(store, task, ("panda",)) == [ids["panda"]]
        with pytest.raises(RuntimeError, match="studio collect --robot hand"):
            _expert_choices(store, "pick_place/bar->blue", ("human",))


def test_the_panda_imitates_hand_demonstrations(tmp_path):
    """Human-Franka: rollouts draw their demonstrations from the simulated hand's episodes only."""
    from studio.data.collect import CollectConfig, collect
    from studio.data.store import EpisodeStore
    from studio.eval.evaluation import evaluate

    task = "pick_place/bar->blue"
    for robot in ("hand", "sawyer"):
        cfg = CollectConfig(
            robot=robot, tasks=[task], episodes=1, image_size=(60, 80), data_dir=str(tmp_path), progress=False
        )
        assert collect(cfg).made == 1
    report = evaluate(
        "oracle", [task], 2, seed=0, data_dir=tmp_path, progress=False, expert_embodiments=["human"]
    )
    assert report["expert_embodiments"] == ["human"] and report["success"] == 1.0
    with EpisodeStore(tmp_path) as store:
        (hand_demo,) = store.episodes(embodiment="human")
        assert {r["expert_episode_id"] for r in report["rows"]} == {hand_demo.id}
