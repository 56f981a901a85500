"""`studio eval` on the command line: task names give their scene, and bad task lists are a clear error."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from studio.eval.evaluation import EvaluationReport, add_arguments, run


def _report(checkpoint: str, **changes) -> EvaluationReport:
    """A Meta-World report with no rollouts, for tests of what ``studio eval`` prints; ``changes`` override fields."""
    empty = EvaluationReport(
        tasks={},
        success=0.0,
        rollouts=0,
        mean_planning_ms=0.0,
        eval_id="e",
        checkpoint=checkpoint,
        robot="sawyer",
        scene="metaworld",
        seed=0,
        replan=0,
        grasp_correction="auto",
        expert_embodiments=("sawyer",),
        episodes_per_task=1,
        wall_s=0.0,
        workers=1,
        rows=(),
    )
    return dataclasses.replace(empty, **changes)


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
    from studio.eval.evaluation import EvaluationInputError, _expert_choices, expert_embodiments_of

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
        # Another embodiment's than the Panda agent's, in demonstration_order (by what they are: human first).
        assert _expert_choices(store, task) == [ids["hand"], ids["sawyer"]]
        assert _expert_choices(store, task, ("human",)) == [ids["hand"]]
        assert _expert_choices(store, task, ("panda",)) == [ids["panda"]]
        with pytest.raises(EvaluationInputError, match="studio collect --robot hand"):
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
    assert report.expert_embodiments == ("human",) and report.success == 1.0
    with EpisodeStore(tmp_path) as store:
        (hand_demo,) = store.episodes(embodiment="human")
        assert {r.expert_episode_id for r in report.rows} == {hand_demo.id}


#: The report's JSON form as ``evaluate`` wrote it when it returned a dict: each key (in order) and its type.
REPORT_JSON_FIELDS = {
    "tasks": dict,
    "success": float,
    "rollouts": int,
    "mean_planning_ms": float,
    "eval_id": str,
    "checkpoint": str,
    "robot": str,
    "scene": str,
    "seed": int,
    "replan": int,
    "grasp_correction": str,
    "expert_embodiments": list,
    "episodes_per_task": int,
    "wall_s": float,
    "workers": int,
    "rows": list,
}
TASK_JSON_FIELDS = {
    "rollouts": int,
    "success": float,
    "reached": float,
    "grasped": float,
    "placed": float,
    "mean_replans": float,
    "mean_planning_ms": float,
    "failure_stages": dict,
}
ROW_JSON_FIELDS = {
    "rollout_id": str,
    "task": str,
    "index": int,
    "seed": int,
    "expert_episode_id": str,
    "success": bool,
    "reached": bool,
    "grasped": bool,
    "placed": bool,
    "failure_stage": type(None),  # the oracle succeeds
    "replans": int,
    "planning_time_s": float,
    "duration_s": float,
    "attempt_stages": list,
    "attempt_planning_s": list,
}


def _shape(d: dict) -> list[tuple[str, type]]:
    return [(key, type(value)) for key, value in d.items()]


def test_the_report_reads_by_attribute_and_its_json_form_keeps_the_dict_shape(tmp_path, capsys):
    """``evaluate`` returns an :class:`EvaluationReport`; its ``to_dict`` (``studio eval --json``, the results
    files) has the keys, order and types of the dict it returned before, and holds the attributes' values."""
    import json

    from studio.data.collect import CollectConfig, collect
    from studio.eval.evaluation import EvaluationReport, TaskBreakdown, evaluate, with_budget

    task = "pick_place/bar->blue"
    cfg = CollectConfig(
        robot="sawyer", tasks=[task], episodes=1, image_size=(60, 80), data_dir=str(tmp_path), progress=False
    )
    assert collect(cfg).made == 1
    report = evaluate("oracle", [task], 1, seed=2, data_dir=tmp_path, progress=False)
    assert isinstance(report, EvaluationReport) and isinstance(report.tasks[task], TaskBreakdown)
    assert (report.success, report.rollouts, report.tasks[task].placed) == (1.0, 1, 1.0)
    assert (report.scene, report.robot, report.seed, report.expert_embodiments) == (
        "pick_place",
        "panda",
        2,
        ("sawyer", "human"),
    )
    (row,) = report.rows
    assert row.task == task and row.success and row.replans == 0

    as_dict = report.to_dict()
    assert _shape(as_dict) == list(REPORT_JSON_FIELDS.items())
    assert _shape(as_dict["tasks"][task]) == list(TASK_JSON_FIELDS.items())
    assert _shape(as_dict["rows"][0]) == list(ROW_JSON_FIELDS.items())
    assert json.loads(json.dumps(as_dict)) == as_dict, "built-ins only: no default= needed to write it"
    assert as_dict["tasks"][task]["success"] == report.tasks[task].success
    assert as_dict["rows"][0]["rollout_id"] == row.rollout_id and as_dict["eval_id"] == report.eval_id
    assert as_dict["expert_embodiments"] == ["sawyer", "human"]
    # A derived budget adds the key saying what it was cut from, nothing else.
    derived = with_budget(report, 0).to_dict()
    assert [k for k in derived if k not in as_dict] == ["derived_from_replan"] and derived[
        "derived_from_replan"
    ] == 0
    # A bound on each plan's execution is said (and kept by a derived budget); unbounded, the key is absent.
    bounded = dataclasses.replace(report, plan_ticks=500)
    assert [k for k in bounded.to_dict() if k not in as_dict] == ["plan_ticks"]
    assert with_budget(bounded, 0).to_dict()["plan_ticks"] == 500


def test_a_negative_plan_tick_bound_is_refused(capsys, tmp_path):
    assert run(_args("--plan-ticks", "-1", "--data-dir", str(tmp_path))) == 2
    assert "--plan-ticks must be >= 0 (0: no bound), got -1" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, bound",
    [
        (
            ["--tasks", "metaworld/door-unlock-v3"],
            500,
        ),  # the scene's protocol: the paper's 500 steps per plan
        (["--tasks", "held-out", "--scene", "metaworld"], 500),
        (["--tasks", "metaworld/door-unlock-v3", "--plan-ticks", "0"], None),  # 0: no bound
        (["--tasks", "metaworld/door-unlock-v3", "--plan-ticks", "300"], 300),
        (["--tasks", "pick_place/bar->blue"], None),  # no protocol bound on the tabletop scenes
    ],
)
def test_studio_eval_bounds_each_plan_as_the_scenes_protocol_unless_told(argv, bound, monkeypatch, capsys):
    """`studio eval` runs a Meta-World task as `studio results` does (each plan at most 500 control ticks) and says
    so in its first line; ``--plan-ticks`` overrides it, 0 lifting the bound."""
    import studio.eval.evaluation as evaluation

    seen = {}

    def fake_evaluate(checkpoint, tasks, *args, plan_ticks=None, **kwargs):
        seen["plan_ticks"] = plan_ticks
        return _report(checkpoint, plan_ticks=plan_ticks)

    monkeypatch.setattr(evaluation, "evaluate", fake_evaluate)
    parser = argparse.ArgumentParser()
    evaluation.add_arguments(parser)
    assert evaluation.run(parser.parse_args(["--checkpoint", "oracle", *argv])) == 0
    assert seen["plan_ticks"] == bound
    assert (f"plan-ticks={bound}" in capsys.readouterr().out) == (bound is not None)


def test_the_demonstrations_drawn_depend_on_what_was_collected_not_on_episode_ids(tmp_path):
    """The same scripted collection stored twice, in other orders and under other ids: every job draws the same
    collection slot in both stores (ids carry the time of storing)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
    from data_fixtures import make_recording

    from studio.data.store import EpisodeStore
    from studio.eval.evaluation import make_jobs, with_demonstrations

    task = "pick_place/bar->blue"
    slots = [(7, i) for i in range(6)]
    drawn = []
    for name, order in (("a", slots), ("b", slots[::-1])):
        with EpisodeStore(tmp_path / name) as store:
            for base, index in order:
                rec = make_recording(task=task, robot="sawyer", seed=base * 100 + index)
                store.add_episode(
                    rec, role="expert", source="scripted", collect_seed=base, collect_index=index
                )
            jobs = with_demonstrations(store, make_jobs([task], 12, seed=3))
            by_id = {m.id: (m.collect_seed, m.collect_index) for m in store.episodes()}
            drawn.append([by_id[j.expert_episode_id] for j in jobs])
    assert drawn[0] == drawn[1] and len(set(drawn[0])) > 2


def test_end_offsets_measure_each_first_plan_against_the_scripted_experts_and_leave_the_rollouts(
    tmp_path, capsys
):
    """``--end-offsets``: each rollout's first plan's last waypoint minus the oracle's (the scripted expert's plan
    for the same scene), summed up per task and printed; the rollouts are those of a run without it, the JSON
    gains the keys only when measured, and the oracle's own plans end where the scripted expert's do."""
    from pathlib import Path

    import numpy as np

    from studio.data.collect import CollectConfig, collect
    from studio.data.store import EpisodeStore
    from studio.eval.evaluation import evaluate
    from studio.eval.oracle import OraclePlanner
    from studio.sim.env import make_env

    from .tiny_checkpoint import write_tiny_checkpoint

    task = "pick_place/bar->blue"
    cfg = CollectConfig(
        robot="sawyer", tasks=[task], episodes=1, image_size=(60, 80), data_dir=str(tmp_path), progress=False
    )
    assert collect(cfg).made == 1
    ck = str(write_tiny_checkpoint(tmp_path / "tiny" / "best.pt"))
    plain = evaluate(ck, [task], 2, seed=3, data_dir=tmp_path, progress=False)
    measured = evaluate(ck, [task], 2, seed=3, data_dir=tmp_path, progress=False, end_offsets=True)

    def outcome(r):
        return (r.task, r.index, r.seed, r.expert_episode_id, r.success, r.failure_stage, r.attempt_stages)

    assert [outcome(r) for r in measured.rows] == [outcome(r) for r in plain.rows]
    assert all(r.end_offset is None for r in plain.rows) and plain.tasks[task].end_offset_mean is None

    env = make_env("pick_place", "panda")
    oracle = OraclePlanner(env)
    try:
        with EpisodeStore(tmp_path) as store:
            for row in measured.rows:
                env.reset(task, row.seed)
                expert_end = oracle.plan(None, None, None, None).waypoints_world[-1, :3]
                (record,) = [
                    r for r in store.catalog.rollouts(eval_id=measured.eval_id) if r.id == row.rollout_id
                ]
                with np.load(Path(record.path) / "plans.npz") as plans:
                    plan_end = plans["plan0_waypoints_world"][-1, :3]
                np.testing.assert_allclose(row.end_offset, plan_end - expert_end, atol=1e-9)
    finally:
        env.close()
    offsets = np.array([r.end_offset for r in measured.rows])
    assert np.linalg.norm(offsets, axis=1).min() > 0.01, (
        "an untrained model does not end where the expert does"
    )
    breakdown = measured.tasks[task]
    np.testing.assert_allclose(breakdown.end_offset_mean, offsets.mean(axis=0))
    np.testing.assert_allclose(breakdown.end_offset_sd, offsets.std(axis=0))
    assert breakdown.end_distance_mean == pytest.approx(np.linalg.norm(offsets, axis=1).mean())

    as_dict, before = measured.to_dict(), plain.to_dict()
    assert list(as_dict["rows"][0]) == [*before["rows"][0], "end_offset"]
    assert list(as_dict["tasks"][task]) == [
        *before["tasks"][task],
        "end_offset_mean",
        "end_offset_sd",
        "end_distance_mean",
        "end_measured",
    ]
    assert breakdown.end_measured == 2
    assert as_dict["rows"][1]["end_offset"] == list(measured.rows[1].end_offset)

    own = evaluate("oracle", [task], 1, seed=3, data_dir=tmp_path, progress=False, end_offsets=True)
    assert own.success == 1.0 and own.rows[0].end_offset == (0.0, 0.0, 0.0)

    assert (
        run(
            _args(
                "--tasks",
                task,
                "--episodes",
                "1",
                "--seed",
                "3",
                "--end-offsets",
                "--no-store",
                "--data-dir",
                str(tmp_path),
            )
        )
        == 0
    )
    out = capsys.readouterr().out.splitlines()
    assert (
        out[-2]
        == "first plan's last waypoint − the scripted expert's, world frame, cm (mean ± sd; distance):"
    )
    assert out[-1] == f"{task:32s} x   +0.0 ±  0.0  y   +0.0 ±  0.0  z   +0.0 ±  0.0  (0.0)"


def test_the_table_is_as_wide_as_the_longest_task_name(monkeypatch, capsys):
    """Meta-World's longer names (``button-press-topdown-wall-v3``) keep the columns and the end offsets lined up."""
    import studio.eval.evaluation as evaluation
    from studio.eval.evaluation import TaskBreakdown

    long_name, short_name = "metaworld/button-press-topdown-wall-v3", "metaworld/reach-v3"
    offsets = {"end_offset_mean": (0.027, -0.047, 0.05), "end_offset_sd": (0.041, 0.088, 0.07)}
    tasks = {
        name: TaskBreakdown(
            4, 0.75, 1.0, 1.0, 0.75, 0.0, 190.0, {}, **offsets, end_distance_mean=0.091, end_measured=n
        )
        for name, n in ((long_name, 4), (short_name, 3))
    }

    def fake_evaluate(checkpoint, task_names, *args, **kwargs):
        return _report(
            checkpoint,
            tasks=tasks,
            success=0.75,
            rollouts=8,
            mean_planning_ms=190.0,
            episodes_per_task=4,
            wall_s=1.0,
        )

    monkeypatch.setattr(evaluation, "evaluate", fake_evaluate)
    assert run(_args("--tasks", f"{long_name},{short_name}", "--end-offsets")) == 0
    lines = capsys.readouterr().out.splitlines()
    header, long_row, short_row, total = lines[1:5]
    assert (
        header.index(" n") + 1
        == long_row.index(" 4 ") + 1
        == short_row.index(" 4 ") + 1
        == total.index(" 8 ") + 1
    )
    assert lines[-2].index(" x ") == lines[-1].index(" x ") == len(long_name)
    assert lines[-2].endswith("x   +2.7 ±  4.1  y   -4.7 ±  8.8  z   +5.0 ±  7.0  (9.1)")
    assert lines[-1].endswith("(9.1; 1 not measured: the scripted expert failed there)")


def test_a_scene_whose_scripted_expert_fails_is_left_out_of_the_end_offsets(monkeypatch):
    """Meta-World's scripted policies fail on a few seeds; there the expert's path ends nowhere worth measuring
    against, so that rollout has no end offset and its task's summary says how many were measured."""
    from types import SimpleNamespace

    import studio.sim.metaworld_experts as metaworld_experts
    from studio.eval import evaluation
    from studio.eval.evaluation import EvalJob, RolloutSummary, summarise
    from studio.eval.oracle import OraclePlanner

    calls = []

    def failing(task, seed, scratch=None, strict=False):
        calls.append((task, seed, strict))
        raise RuntimeError(f"the scripted policy of {task} failed on seed {seed}")

    class Env:
        scene = "metaworld"
        task = SimpleNamespace(name="button-press-v3")

        def reset(self, task, seed):
            self.reset_to, self.seed = (task, seed), seed

    monkeypatch.setattr(metaworld_experts, "expert_waypoints", failing)
    env = Env()
    reference = OraclePlanner(env, strict=True)
    monkeypatch.setattr(reference, "_scratch", object())  # the oracle's scratch scene, not built here
    monkeypatch.setitem(evaluation._W, "reference", reference)
    assert evaluation._expert_end(env, EvalJob("metaworld/button-press-v3", 0, 3, 0)) is None
    assert calls == [("button-press-v3", 3, True)] and env.reset_to == ("metaworld/button-press-v3", 3)

    def row(index, offset):
        return RolloutSummary(
            f"r{index}",
            "metaworld/button-press-v3",
            index,
            index,
            "e",
            True,
            True,
            True,
            True,
            None,
            0,
            0.2,
            1.0,
            end_offset=offset,
        )

    (breakdown,) = summarise(
        [row(0, (0.02, -0.01, 0.1)), row(1, None), row(2, (0.04, 0.01, 0.1))]
    ).tasks.values()
    assert breakdown.end_measured == 2 and breakdown.rollouts == 3
    assert breakdown.end_offset_mean == pytest.approx((0.03, 0.0, 0.1))
    assert breakdown.end_offsets_text().endswith("; 1 not measured: the scripted expert failed there)")


def test_studio_eval_says_what_is_wrong_with_its_input_before_any_rollout(tmp_path, capsys):
    """No checkpoint file, a file that is not a checkpoint, a policy of another scene, no demonstration of the
    task: one line saying so (and what to do), exit status 2, no traceback and no rollout stored."""
    from studio.data.paths import SHIPPED_POLICY_DIR
    from studio.data.store import EpisodeStore

    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("hello")
    shipped_metaworld = str(SHIPPED_POLICY_DIR / "metaworld-cpu.pt")
    task = "pick_place/bar->blue"
    cases = [
        (
            str(tmp_path / "missing.pt"),
            f"no checkpoint file '{tmp_path / 'missing.pt'}' (give a .pt file or 'oracle')",
        ),
        (str(not_a_checkpoint), f"{not_a_checkpoint} is not a checkpoint ("),
        (shipped_metaworld, f"{shipped_metaworld} was trained on metaworld tasks, not on scene 'pick_place'"),
        (
            "oracle",
            f"no expert demonstration of '{task}' by sawyer or human in the store; collect some with: "
            f"studio collect --robot sawyer --tasks {task}",
        ),
    ]
    for checkpoint, said in cases:
        parser = argparse.ArgumentParser()
        add_arguments(parser)
        args = parser.parse_args(
            ["--checkpoint", checkpoint, "--tasks", task, "--data-dir", str(tmp_path / "d")]
        )
        assert run(args) == 2, checkpoint
        err = capsys.readouterr().err
        assert err.startswith(f"studio eval: {said}") and len(err.splitlines()) == 1, err
    with EpisodeStore(tmp_path / "d") as store:
        assert store.catalog.rollouts() == []
