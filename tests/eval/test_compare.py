"""`studio compare`: A and B on the identical episodes, the table's difference column, its order and totals, the
rows of stored evaluations, and bad input refused before anything runs."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest

from studio.data.catalog import RolloutRecord
from studio.data.collect import CollectConfig, collect
from studio.data.store import EpisodeStore
from studio.eval.compare import (
    CompareRow,
    Comparison,
    Outcome,
    compare,
    order_rows,
    pair_rollouts,
    render_markdown,
    stored_evaluations,
    totals,
)
from studio.eval.evaluation import make_jobs, with_demonstrations

from .tiny_checkpoint import write_tiny_checkpoint

TASK = "pick_place/bar->blue"


def _row(index: int, a: bool, b: bool, task: str = TASK) -> CompareRow:
    return CompareRow(
        task,
        index,
        100 + index,
        f"demo{index}",
        Outcome(f"ra{index}", a, None if a else "grasp"),
        Outcome(f"rb{index}", b, None if b else "reach"),
    )


# ---------------------------------------------------------------------------------------------- the table
def test_the_difference_column_says_which_side_succeeded():
    assert [
        _row(0, True, False).difference,
        _row(1, False, True).difference,
        _row(2, True, True).difference,
        _row(3, False, False).difference,
    ] == ["A only", "B only", "both", "neither"]
    assert _row(0, True, False).a.mark == "✔" and _row(0, True, False).b.mark == "✘ reach"


def test_differing_rows_come_first_then_by_task_and_index():
    rows = [
        _row(0, True, True),
        _row(1, False, True),
        _row(2, False, False),
        _row(3, True, False),
        _row(4, False, True, task="pick_place/bar->yellow"),
        _row(5, True, False),
    ]
    ordered = [(r.task.split(">")[1], r.index, r.difference) for r in order_rows(rows)]
    assert ordered == [
        ("blue", 3, "A only"),
        ("blue", 5, "A only"),
        ("blue", 1, "B only"),
        ("yellow", 4, "B only"),
        ("blue", 0, "both"),
        ("blue", 2, "neither"),
    ]


def test_totals_and_markdown():
    rows = order_rows([_row(0, True, True), _row(1, False, True), _row(2, True, False), _row(3, True, False)])
    t = totals(rows)
    assert (t.a_success, t.b_only) == (0.75, 1)
    assert json.loads(json.dumps(t.to_dict())) == {
        "episodes": 4,
        "a_successes": 3,
        "b_successes": 2,
        "a_success": 0.75,
        "b_success": 0.5,
        "a_only": 2,
        "b_only": 1,
        "both": 1,
        "neither": 0,
    }
    text = render_markdown(rows, "osvi|wm", "ablation")
    lines = text.splitlines()
    assert lines[0] == "| task | # | seed | demonstration | A: osvi\\|wm | B: ablation | difference |"
    assert lines[2] == f"| {TASK} | 2 | 102 | `demo2` | ✔ | ✘ reach | **A only** |"
    assert lines[5] == f"| {TASK} | 0 | 100 | `demo0` | ✔ | ✔ | both |"
    assert "**A 75.0%** (3 / 4, osvi\\|wm) · **B 50.0%** (2 / 4, ablation) · A only 2 · B only 1" in lines[-1]
    assert CompareRow.from_dict(rows[0].to_dict()) == rows[0] and rows[0].to_dict()["difference"] == "A only"


def test_stored_evaluations_pair_on_task_seed_and_demonstration():
    def rec(rid, eval_id, seed, demo, success, ck="run/best"):
        return RolloutRecord(
            id=rid,
            task=TASK,
            success=success,
            checkpoint_id=ck,
            expert_episode_id=demo,
            seed=seed,
            failure_stage=None if success else "grasp",
            eval_id=eval_id,
            extra={"index": seed},
        )

    a = [rec("a1", "e1", 1, "d1", True), rec("a2", "e1", 2, "d2", True), rec("a3", "e1", 3, "d3", False)]
    b = [
        rec("b1", "e2", 1, "d1", False, None),
        rec("b2", "e2", 2, "dX", True, None),
        rec("b3", "e2", 3, "d3", False, None),
    ]
    rows = order_rows(pair_rollouts(a, b))
    assert [(r.seed, r.a.rollout_id, r.b.rollout_id, r.difference) for r in rows] == [
        (1, "a1", "b1", "A only"),
        (3, "a3", "b3", "neither"),
    ], "seed 2 had another demonstration: not the same episode"

    class Catalog:
        def rollouts(self, limit=None, eval_id=None):
            return [r for r in a + b if eval_id in (None, r.eval_id)]

    evals = {e.eval_id: e for e in stored_evaluations(Catalog())}
    assert evals["e1"].checkpoint == "run/best" and evals["e2"].checkpoint == "oracle"
    assert evals["e1"].rollouts == 3 and evals["e1"].complete


# ---------------------------------------------------------------------------------------------- running it
@pytest.fixture(scope="module")
def store_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare") / "data"
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=[TASK],
            episodes=3,
            data_dir=str(root),
            progress=False,
            image_size=(120, 160),
        )
    )
    return root


def test_a_and_b_roll_out_the_same_episodes_and_every_rollout_is_stored(store_root, tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    ck = str(write_tiny_checkpoint(tmp_path / "tiny" / "best.pt"))
    with EpisodeStore(store_root) as store:
        expected = with_demonstrations(store, make_jobs([TASK], 3, 5))
    progress = []

    def on_episode(done, total, row):
        progress.append((done, total, row.difference))
        if (
            done == 1
        ):  # a demonstration recorded meanwhile changes nothing: the episodes were drawn at the start
            with EpisodeStore(store_root) as store:
                store.add_episode(
                    make_recording(task=TASK, robot="sawyer", seed=99), role="expert", source="teleop"
                )

    result = compare("oracle", ck, [TASK], 3, 5, data_dir=store_root, on_episode=on_episode)
    assert progress == [
        (1, 3, "A only"),
        (2, 3, "A only"),
        (3, 3, "A only"),
    ]  # the untrained model reaches nothing
    assert [(r.task, r.index, r.seed, r.expert_episode_id) for r in result.rows] == [
        (j.task, j.index, j.env_seed, j.expert_episode_id) for j in expected
    ]
    assert (result.label_a, result.label_b) == ("oracle", "tiny/best")
    t = result.totals()
    assert (t.a_success, t.b_success, t.a_only, t.b_only) == (1.0, 0.0, 3, 0)
    with EpisodeStore(store_root) as store:
        side_a = store.catalog.rollouts(eval_id=result.eval_ids[0])
        side_b = store.catalog.rollouts(eval_id=result.eval_ids[1])
        assert len(side_a) == len(side_b) == 3
        key = sorted((r.task, r.seed, r.expert_episode_id) for r in side_a)
        assert key == sorted((r.task, r.seed, r.expert_episode_id) for r in side_b), "identical episodes"
        assert {r.checkpoint_id for r in side_a} == {None} and {r.checkpoint_id for r in side_b} == {
            "tiny/best"
        }
        for r in side_a + side_b:
            assert r.extra["compare_id"] == result.compare_id and r.extra["compare_episodes"] == 3
            assert r.episode_id is not None and store.load_frames(r.episode_id).shape[0] >= 20, (
                "kept to be replayed"
            )
        ticks = side_a[0].extra["stage_ticks"]
        assert 0 < ticks["reached"] <= ticks["grasped"] <= ticks["placed"] <= side_a[0].num_steps
        evals = {e.eval_id: e for e in stored_evaluations(store.catalog)}
        assert evals[result.eval_ids[1]].complete and evals[result.eval_ids[1]].label == "tiny/best"
    as_json = json.loads(json.dumps(result.to_dict()))
    assert as_json["rows"][0]["difference"] == "A only" and as_json["totals"]["a_only"] == 3
    assert list(as_json) == [  # the compare job's result on the bus and the JSON beside --out: this shape
        "compare_id",
        "checkpoint_a",
        "checkpoint_b",
        "label_a",
        "label_b",
        "scene",
        "robot",
        "tasks",
        "episodes",
        "seed",
        "replan",
        "workers",
        "wall_s",
        "eval_ids",
        "totals",
        "rows",
    ]
    assert as_json["tasks"] == [TASK] and as_json["eval_ids"] == list(result.eval_ids)


def test_a_stopped_comparison_says_so_and_its_rollouts_are_marked_incomplete(store_root):
    seen = []
    with pytest.raises(InterruptedError, match="stopped after 2 of 4 rollouts"):
        compare(
            "oracle",
            "oracle",
            [TASK],
            2,
            9,
            data_dir=store_root,
            on_episode=lambda *a: seen.append(a),
            should_stop=lambda: len(seen) > 0,
        )
    with EpisodeStore(store_root) as store:
        stopped = [e for e in stored_evaluations(store.catalog) if not e.complete]
    assert sorted(e.rollouts for e in stopped) == [1, 1] and all(e.planned == 2 for e in stopped)
    assert "1 of 2 rollouts (stopped)" in stopped[0].describe()


# ---------------------------------------------------------------------------------------------- bad input
def _cli(*argv: str) -> int:
    from studio.cli import main

    return main(["compare", *argv])


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (("--a", "missing.pt", "--b", "oracle"), "no checkpoint file 'missing.pt'"),
        (
            ("--a", "oracle", "--b", "oracle", "--tasks", "pick_place/ball->red"),
            "unknown task 'pick_place/ball->red'",
        ),
        (
            ("--a", "oracle", "--b", "oracle", "--tasks", "pick_place/cube->red,push/red-forward"),
            "belongs to scene",
        ),
        (("--a", "oracle", "--b", "oracle", "--episodes", "0"), "--episodes must be at least 1"),
        (("--a", "oracle", "--b", "oracle", "--tasks", "pick_place/bar->yellow"), "no expert demonstration"),
        (
            ("--a", "SHIPPED", "--b", "oracle", "--scene", "push"),
            "was trained on pick_place tasks, not on scene 'push'",
        ),
        (("--a", "README", "--b", "oracle"), "is not a checkpoint"),
        (("--a", "oracle", "--b", "oracle", "--expert-embodiment", "robot"), "unknown embodiment(s) robot"),
        (
            ("--a", "oracle", "--b", "oracle", "--tasks", TASK, "--expert-embodiment", "panda"),
            f"no expert demonstration of '{TASK}' by panda",
        ),
    ],
)
def test_bad_input_exits_2_with_one_line_before_any_rollout(argv, says, store_root, capsys):
    from studio.data.paths import SHIPPED_POLICY_DIR

    repo = Path(__file__).resolve().parents[2]
    subst = {"SHIPPED": str(SHIPPED_POLICY_DIR / "pick-place-cpu.pt"), "README": str(repo / "README.md")}
    argv = tuple(subst.get(a, a) for a in argv)
    with EpisodeStore(store_root) as store:
        before = len(store.catalog.rollouts())
    assert _cli(*argv, "--data-dir", str(store_root)) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and err.startswith("studio compare: ") and "\n" not in err, err
    with EpisodeStore(store_root) as store:
        assert len(store.catalog.rollouts()) == before


def test_the_command_writes_the_table_and_its_json(store_root, tmp_path, capsys):
    out = tmp_path / "cmp.md"
    assert (
        _cli(
            "--a",
            "oracle",
            "--b",
            "oracle",
            "--label-b",
            "oracle again",
            "--tasks",
            TASK,
            "--episodes",
            "1",
            "--data-dir",
            str(store_root),
            "--out",
            str(out),
        )
        == 0
    )
    text = out.read_text()
    assert "| A: oracle | B: oracle again | difference |" in text and "| ✔ | ✔ | both |" in text
    assert text in capsys.readouterr().out
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["totals"]["both"] == 1 and data["rows"][0]["a"]["success"] is True


@pytest.mark.parametrize(("task", "bound"), [("metaworld/door-unlock-v3", 500), (TASK, None)])
def test_both_sides_run_under_the_scenes_protocol(task, bound, tmp_path, monkeypatch):
    """A Meta-World comparison bounds each plan at the paper's 500 control ticks, as `studio eval` and `studio
    results` do; the tabletop scenes have no bound."""
    import dataclasses

    import studio.eval.evaluation as evaluation

    seen = []

    def drawn(store, jobs, experts):
        return [dataclasses.replace(j, expert_episode_id="demo") for j in jobs]

    def stop_before_rolling_out(work, **kwargs):
        seen.extend(side.plan_ticks for _, side in work)
        raise InterruptedError("stopped before any rollout")

    monkeypatch.setattr(evaluation, "with_demonstrations", drawn)
    monkeypatch.setattr(evaluation, "run_rollouts", stop_before_rolling_out)
    with pytest.raises(InterruptedError, match="stopped before any rollout"):
        compare("oracle", "oracle", [task], 1, 0, data_dir=tmp_path / "data")
    assert seen == [bound, bound]
    said = Comparison(
        "c", "oracle", "oracle", "A", "B", "metaworld", "sawyer", (task,), 1, 0, 3, 1, 1.0, (), bound
    )
    assert ("each plan at most 500 control ticks" in said.markdown()) == (bound is not None)
    assert said.to_dict().get("plan_ticks") == bound
