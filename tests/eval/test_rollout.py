"""Rollouts and evaluation: deterministic for a seed, re-planning inside one episode, stored records reload."""

import json
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from studio.data.collect import CollectConfig, collect
from studio.data.splits import resolve_tasks
from studio.data.store import EpisodeStore
from studio.eval.evaluation import evaluate, make_jobs
from studio.eval.oracle import OraclePlanner
from studio.eval.rollout import failure_stage, grasp_controller, run_rollout
from studio.sim.env import SimEnv

from .tiny_checkpoint import write_tiny_checkpoint


class MissThenOracle:
    """Plans empty air first, then the true waypoints: exercises re-planning."""

    def __init__(self, env):
        self.oracle = OraclePlanner(env)
        self.calls = 0
        self.env = env
        self.seen_steps = []

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        self.calls += 1
        self.seen_steps.append(self.env.steps)
        if self.calls == 1:
            wps = np.array(
                [
                    [0.3, 0.8, 0.1, 1],
                    [0.3, 0.8, 0.15, 1],
                    [0.3, 0.8, 0.15, 0],
                    [0.3, 0.8, 0.15, 0],
                    [0.3, 0.8, 0.2, 0],
                ],
                dtype=float,
            )
            return type("P", (), {"waypoints_world": wps})()
        return self.oracle.plan(expert_frames, agent_frame, K, T_world_cam)


def _collect_bar_to_blue(root, episodes: int) -> None:
    """Scripted Sawyer demonstrations of the held-out pick_place/bar->blue at 120×160, into ``root``."""
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=["pick_place/bar->blue"],
            episodes=episodes,
            data_dir=str(root),
            progress=False,
            image_size=(120, 160),
        )
    )


@pytest.fixture(scope="module")
def env():
    e = SimEnv("pick_place", "panda")
    yield e
    e.close()


def test_replanning_stays_in_the_same_episode(env):
    planner = MissThenOracle(env)
    frames = np.zeros((10, 240, 320, 3), np.uint8)
    out = run_rollout(env, planner, frames, "pick_place/bar->blue", 5, replans=0)
    assert not out.success and out.failure_stage == "reach" and len(out.plans) == 1

    planner = MissThenOracle(env)
    out = run_rollout(env, planner, frames, "pick_place/bar->blue", 5, replans=2)
    assert out.success and out.replans == 1
    # The breakdown after each attempt: the first missed everything, the second placed the bar.
    assert out.attempt_stages == [
        {"reached": False, "grasped": False, "placed": False},
        {"reached": True, "grasped": True, "placed": True},
    ]
    # The second plan was made mid-episode: the tick counter kept running, no reset in between.
    assert planner.seen_steps[0] == 0 and planner.seen_steps[1] > 0
    assert out.plans[1].start_tick == planner.seen_steps[1]
    times = out.recording.arrays["time"]
    assert np.all(np.diff(times) > 0), "time must increase monotonically through a re-plan"
    kinds = [k for k, _ in out.events]
    assert kinds.count("planning") == 2 and "replanning" in kinds and kinds[-1] == "outcome"


def test_a_plan_cut_at_its_tick_bound_is_a_failed_attempt_and_the_next_plan_continues(env):
    """The paper's protocol bounds each plan's execution (500 steps in Meta-World): the oracle's plan, given 40
    ticks, is cut before it reaches the bar; the re-plan starts at tick 40 of the same episode, and given 40 more
    ticks is cut too. Unbounded, the same rollout succeeds."""
    frames = np.zeros((10, 240, 320, 3), np.uint8)
    oracle = OraclePlanner(env)
    whole = run_rollout(env, oracle, frames, "pick_place/bar->blue", 5)
    assert whole.success and whole.recording.arrays["time"].shape[0] > 100
    cut = run_rollout(env, oracle, frames, "pick_place/bar->blue", 5, replans=1, plan_ticks=40)
    assert not cut.success and cut.failure_stage != "cancelled" and len(cut.plans) == 2
    assert [p.start_tick for p in cut.plans] == [0, 40]
    assert env.steps == 80  # both plans used their whole bound, no more
    assert [k for k, _ in cut.events].count("plan time up") == 2
    with pytest.raises(ValueError, match="plan_ticks must be >= 1"):
        run_rollout(env, oracle, frames, "pick_place/bar->blue", 5, plan_ticks=0)


class TableTop:
    """Plans five waypoints that the open hand cannot reach (its fingertips meet the table 2 cm above them)."""

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        wps = np.array([[x, 0.5, 0.012, 0.0] for x in (-0.2, -0.1, 0.0, 0.1, 0.2)])
        return type("P", (), {"waypoints_world": wps})()


def test_within_a_plans_tick_bound_each_waypoint_gets_its_share_and_a_blocked_one_is_left(env):
    """Bounded as the paper's protocol is, a plan's K waypoints each get ``plan_ticks // K`` ticks (the reference's
    ``try_limit``) and one where the hand has stopped short is left: the five blocked waypoints are all tried within
    the bound. Unbounded, each takes the controller's whole 120 ticks."""
    frames = np.zeros((10, 240, 320, 3), np.uint8)
    unbounded = run_rollout(env, TableTop(), frames, "pick_place/bar->blue", 5)
    assert env.steps == 5 * 120 and not any(k == "stalled" for k, _ in unbounded.events)
    bounded = run_rollout(env, TableTop(), frames, "pick_place/bar->blue", 5, plan_ticks=250)
    waypoints = [k for k, _ in bounded.events if k == "waypoint"]
    assert len(waypoints) == 5 and env.steps < 250 and "plan time up" not in [k for k, _ in bounded.events]
    assert sum(k == "stalled" for k, _ in bounded.events) >= 3


class BelowTheTable:
    """Plans a waypoint below the table and one past the workspace's far edge (as a guided plan may)."""

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        wps = np.array([[0.0, 0.5, 0.2, 0.0], [0.0, 0.5, -0.2, 0.0], [0.0, 1.4, 0.2, 0.0]])
        return type("P", (), {"waypoints_world": wps})()


def test_each_plan_keeps_the_targets_the_controller_commanded_beside_the_prediction(env, tmp_path):
    """What the page draws and Inspect replays is where the arm was sent: the stored plan has the model's waypoints
    and the commanded ones (clipped to the workspace), and the live "planned" event carries both."""
    from studio.eval.rollout import store_rollout

    frames = np.zeros((10, 240, 320, 3), np.uint8)
    out = run_rollout(env, BelowTheTable(), frames, "pick_place/bar->blue", 5)
    plan = out.plans[0]
    assert np.allclose(
        plan.waypoints_commanded[:, :3], [[0.0, 0.5, 0.2], [0.0, 0.5, 0.012], [0.0, 0.95, 0.2]]
    )
    (planned,) = [info for kind, info in out.events if kind == "planned"]
    assert np.allclose(planned["commanded"], plan.waypoints_commanded)
    assert np.allclose(planned["waypoints"], plan.waypoints_world)
    with EpisodeStore(tmp_path / "data") as store:
        record = store_rollout(store, out, expert_episode_id=None, checkpoint_id=None)
        with np.load(Path(record.path) / "plans.npz") as stored:
            assert np.allclose(stored["plan0_waypoints_commanded"], plan.waypoints_commanded)
            assert np.allclose(stored["plan0_waypoints_world"], plan.waypoints_world)


def test_failure_stage_order():
    assert failure_stage({"reached": True, "grasped": True, "placed": True}) is None
    assert failure_stage({"reached": True, "grasped": False, "placed": False}) == "grasp"
    assert failure_stage({"reached": True, "grasped": True, "placed": False}) == "place"


def test_jobs_are_deterministic_and_tasks_resolve():
    assert make_jobs(["a", "b"], 3, 7) == make_jobs(["a", "b"], 3, 7)
    assert make_jobs(["a"], 3, 7) != make_jobs(["a"], 3, 8)
    assert resolve_tasks("pick_place", "held-out") == ["pick_place/bar->blue", "pick_place/bar->yellow"]
    with pytest.raises(ValueError, match="unknown task"):
        resolve_tasks("pick_place", "pick_place/ball->red")


def test_evaluation_is_deterministic_and_stores_rollouts(tmp_path):
    _collect_bar_to_blue(tmp_path, 2)
    a = evaluate("oracle", ["pick_place/bar->blue"], 2, seed=3, data_dir=tmp_path, progress=False)
    b = evaluate("oracle", ["pick_place/bar->blue"], 2, seed=3, data_dir=tmp_path, progress=False)
    strip = [(r.seed, r.expert_episode_id, r.success, r.failure_stage) for r in a.rows]
    assert strip == [(r.seed, r.expert_episode_id, r.success, r.failure_stage) for r in b.rows]
    assert a.success == 1.0
    with EpisodeStore(tmp_path) as store:
        rows = store.catalog.rollouts(task="pick_place/bar->blue")
        assert len(rows) == 4
        r = rows[0]
        frames = store.load_frames(r.episode_id)
        assert frames.shape[0] >= 20
        plans = np.load(os.path.join(r.path, "plans.npz"))
        assert plans["plan0_waypoints_world"].shape == (5, 4)


def test_missing_demonstrations_give_a_clear_error(tmp_path):
    from studio.eval.evaluation import EvaluationInputError

    with pytest.raises(EvaluationInputError, match="no expert demonstration"):
        evaluate("oracle", ["pick_place/bar->yellow"], 1, seed=0, data_dir=tmp_path, progress=False)


def test_evaluating_a_checkpoint_file_registers_it_for_the_rollouts(tmp_path):
    root = tmp_path / "data"
    _collect_bar_to_blue(root, 1)
    ck = write_tiny_checkpoint(tmp_path / "run-a" / "best.pt")
    for _ in range(2):  # the second evaluation finds the registration made by the first
        report = evaluate(str(ck), ["pick_place/bar->blue"], 1, seed=0, data_dir=root, progress=False)
        assert report.rows[0].planning_time_s > 0
    with EpisodeStore(root) as store:
        rows = store.catalog.rollouts()
        assert [r.checkpoint_id for r in rows] == ["run-a/best", "run-a/best"]
        (record,) = store.catalog.checkpoints("run-a")
        assert record.path == str(ck.resolve()) and record.step == 7
    from studio.eval.evaluation import EvaluationInputError

    with pytest.raises(EvaluationInputError, match="no checkpoint file"):
        evaluate(
            str(tmp_path / "missing.pt"), ["pick_place/bar->blue"], 1, seed=0, data_dir=root, progress=False
        )


def test_a_guided_policys_rollouts_keep_the_null_plan_beside_each_plan(tmp_path):
    root = tmp_path / "data"
    _collect_bar_to_blue(root, 1)
    for name, g in (("plain", 1.0), ("guided", 3.0)):
        ck = write_tiny_checkpoint(tmp_path / name / "best.pt", guidance=g)
        evaluate(str(ck), ["pick_place/bar->blue"], 1, seed=0, replan=1, data_dir=root, progress=False)
    with EpisodeStore(root) as store:
        stored = {
            r.checkpoint_id: np.load(os.path.join(r.path, "plans.npz")) for r in store.catalog.rollouts()
        }
    plain, guided = stored["plain/best"], stored["guided/best"]
    assert not [k for k in plain if "null" in k]
    n_plans = sum(k.endswith("_waypoints_world") and "null" not in k for k in guided)
    assert n_plans == 2  # the untrained policy fails and re-plans once
    for i in range(n_plans):
        null, plan = guided[f"plan{i}_null_waypoints_world"], guided[f"plan{i}_waypoints_world"]
        assert null.shape == plan.shape == (5, 4) and np.isfinite(null).all()
        # guidance moved the plan away from the null one
        assert np.abs(null[:, :3] - plan[:, :3]).max() > 1e-6
        # ungated, every plan is guided; the demonstration's gain is stored with each
        assert bool(guided[f"plan{i}_guided"]) and float(guided[f"plan{i}_guidance_gain"]) > 0
        assert f"plan{i}_guidance_surprise" not in guided  # no surprise gate, no surprise
        assert float(guided[f"plan{i}_guidance_scale"]) == 3.0
    assert not [k for k in plain if "scale" in k]


def test_a_surprise_gated_policys_rollouts_store_the_surprise_that_guided_them(tmp_path):
    root = tmp_path / "data"
    _collect_bar_to_blue(root, 1)
    # no gain reaches a gate of 100, every surprise a surprise gate of 1e-6
    ck = write_tiny_checkpoint(
        tmp_path / "p" / "best.pt",
        guidance=3.0,
        planning=("model.guidance_gate=100", "model.surprise_gate=1e-6", "model.surprise_guidance=2"),
    )
    evaluate(str(ck), ["pick_place/bar->blue"], 1, seed=0, replan=1, data_dir=root, progress=False)
    with EpisodeStore(root) as store:
        (row,) = store.catalog.rollouts()
        plans = np.load(os.path.join(row.path, "plans.npz"))
    assert len(plans["plan_start_ticks"]) == 2
    for i in range(2):
        assert bool(plans[f"plan{i}_guided"]) and float(plans[f"plan{i}_guidance_gain"]) < 100
        assert float(plans[f"plan{i}_guidance_surprise"]) > 0
        assert float(plans[f"plan{i}_guidance_scale"]) == 2.0  # the surprise gate's own scale


def test_a_smaller_replan_budget_is_the_larger_budgets_rollouts_cut_short(tmp_path):
    """`with_budget` gives exactly what evaluating with fewer re-plans gives (same seeds, same episodes)."""
    from studio.eval.evaluation import with_budget

    root = tmp_path / "data"
    _collect_bar_to_blue(root, 1)
    ck = str(write_tiny_checkpoint(tmp_path / "run" / "best.pt"))
    two = evaluate(ck, ["pick_place/bar->blue"], 2, seed=1, replan=2, data_dir=root, progress=False)
    zero = evaluate(ck, ["pick_place/bar->blue"], 2, seed=1, replan=0, data_dir=root, progress=False)
    assert max(r.replans for r in two.rows) == 2  # the untrained policy fails and re-plans
    derived = with_budget(two, 0)
    fields = (
        "task",
        "index",
        "seed",
        "expert_episode_id",
        "success",
        "reached",
        "grasped",
        "placed",
        "failure_stage",
        "replans",
        "attempt_stages",
    )
    assert [{k: getattr(r, k) for k in fields} for r in derived.rows] == [
        {k: getattr(r, k) for k in fields} for r in zero.rows
    ]
    assert derived.replan == 0 and derived.derived_from_replan == 2 and derived.success == zero.success
    assert with_budget(two, 2).rows == two.rows
    with pytest.raises(ValueError, match="cannot derive"):
        with_budget(zero, 1)


def test_results_command_writes_a_table_of_held_out_success(tmp_path, capsys):
    from studio.cli import main

    root = tmp_path / "data"
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=["test"],
            episodes=1,
            data_dir=str(root),
            progress=False,
            image_size=(120, 160),
        )
    )
    out = tmp_path / "results.md"
    assert (
        main(
            [
                "results",
                "--policy",
                "oracle=oracle",
                "--episodes",
                "1",
                "--replan",
                "0",
                "1",
                "--workers",
                "1",
                "--data-dir",
                str(root),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    text = out.read_text()
    assert "pick_place/bar->blue" in text and "pick_place/bar->yellow" in text
    rows = [line for line in text.splitlines() if line.startswith("| oracle")]
    assert len(rows) == 2 and all("**100.0%**" in r for r in rows), text  # the oracle's plans succeed
    assert len(json.loads(out.with_suffix(".json").read_text())) == 2
    with pytest.raises(SystemExit):
        main(["results", "--policy", "no-equals-sign"])
    assert "NAME=CHECKPOINT" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["results", "--policy", "oracle=oracle", "--grasp-correction", "sideways"])
    assert "--grasp-correction: invalid choice" in capsys.readouterr().err


def test_grasp_correction_modes_set_the_controller():
    auto = {scene: grasp_controller(scene) for scene in ("pick_place", "metaworld", "push")}
    assert auto["pick_place"].grasp_correction and auto["pick_place"].correct_grasp_height
    assert auto["metaworld"].grasp_correction and auto["metaworld"].correct_grasp_height
    assert not auto["push"].grasp_correction
    centre = grasp_controller("pick_place", "centre")
    assert centre.grasp_correction and not centre.correct_grasp_height
    assert grasp_controller("push", "height").grasp_correction
    assert not grasp_controller("metaworld", "off").grasp_correction
    with pytest.raises(ValueError, match="unknown grasp correction 'sideways'"):
        grasp_controller("pick_place", "sideways")


def test_an_evaluation_without_grasp_correction_says_so_and_grasps_as_planned(tmp_path):
    """The same scenes and demonstrations with the correction off: recorded in the report and on every rollout,
    and no rollout looks through the wrist camera."""
    root = tmp_path / "data"
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=["test"],
            episodes=1,
            data_dir=str(root),
            progress=False,
            image_size=(120, 160),
        )
    )
    tasks = ["pick_place/bar->blue"]
    report = evaluate("oracle", tasks, 1, 0, data_dir=str(root), progress=False, grasp="off")
    assert report.grasp_correction == "off"
    with EpisodeStore(root) as store:
        (rollout,) = store.catalog.rollouts()
        assert rollout.extra["grasp_correction"] == "off"
        events = json.loads((Path(rollout.path) / "events.json").read_text())
    assert events and not any(kind == "grasp_correction" for kind, _ in events)
    auto = evaluate("oracle", tasks, 1, 0, data_dir=str(root), progress=False)
    assert auto.grasp_correction == "auto"
    with EpisodeStore(root) as store:
        (rollout,) = [r for r in store.catalog.rollouts() if r.eval_id == auto.eval_id]
        events = json.loads((Path(rollout.path) / "events.json").read_text())
    assert any(kind == "grasp_correction" for kind, _ in events), "pick-and-place corrects grasps by default"
    with pytest.raises(ValueError, match="unknown grasp correction"):
        evaluate("oracle", tasks, 1, 0, data_dir=str(root), progress=False, grasp="sideways")


def test_a_rollout_does_not_depend_on_the_number_of_evaluation_workers(tmp_path):
    """The same (checkpoint, task, seed, demonstration) gives the same rollout, bit for bit, whether one process
    runs every rollout or two share them: each plans on a fixed number of torch threads. (It once followed
    cores ÷ workers; the shipped policy's plans made on 1 and on 2 threads differ by ~5e-8 — an untrained model's
    happen not to.)"""
    import torch

    from studio.data.paths import SHIPPED_POLICY_DIR

    root = tmp_path / "data"
    _collect_bar_to_blue(root, 2)
    ck = str(SHIPPED_POLICY_DIR / "pick-place-cpu.pt")
    threads = torch.get_num_threads()
    one = evaluate(ck, ["pick_place/bar->blue"], 2, seed=4, workers=1, data_dir=root, progress=False)
    assert torch.get_num_threads() == threads, (
        "an in-process evaluation leaves the caller's torch threads alone"
    )
    two = evaluate(ck, ["pick_place/bar->blue"], 2, seed=4, workers=2, data_dir=root, progress=False)
    assert [(r.seed, r.expert_episode_id) for r in one.rows] == [
        (r.seed, r.expert_episode_id) for r in two.rows
    ]
    with EpisodeStore(root) as store:
        rollouts = {r.id: r for r in store.catalog.rollouts()}
        for a, b in zip(one.rows, two.rows, strict=True):
            ra, rb = rollouts[a.rollout_id], rollouts[b.rollout_id]
            with (
                np.load(os.path.join(ra.path, "plans.npz")) as pa,
                np.load(os.path.join(rb.path, "plans.npz")) as pb,
            ):
                assert np.array_equal(pa["plan0_waypoints_world"], pb["plan0_waypoints_world"])
            _, _, xa = store.load_arrays(ra.episode_id)
            _, _, xb = store.load_arrays(rb.episode_id)
            assert np.array_equal(xa["qpos"], xb["qpos"]), "the same plan, executed the same way"
            assert ra.extra["stage_ticks"] == rb.extra["stage_ticks"]


@pytest.mark.slow
def test_the_same_collection_and_evaluation_in_two_fresh_data_directories_give_the_same_table(tmp_path):
    """An evaluation is a function of its seeds and of what the demonstrations show: the same `collect` into two
    fresh data directories (other episode ids, other times) and the same evaluation of the shipped policy give
    the same demonstrations, plans and outcomes, row for row. (Which demonstration a job draws no longer follows
    the ids' order: tests/eval/test_evaluation.py stores the same slots in opposite orders.)"""
    from studio.data.paths import SHIPPED_POLICY_DIR

    ck = str(SHIPPED_POLICY_DIR / "pick-place-cpu.pt")
    tables = []
    for name in ("first", "second"):
        root = tmp_path / name
        _collect_bar_to_blue(root, 3)
        report = evaluate(ck, ["pick_place/bar->blue"], 4, seed=6, data_dir=root, progress=False)
        with EpisodeStore(root) as store:
            slot = {m.id: (m.collect_seed, m.collect_index) for m in store.episodes()}
            plans = {}
            for r in store.catalog.rollouts():
                with np.load(os.path.join(r.path, "plans.npz")) as p:
                    plans[r.id] = p["plan0_waypoints_world"].round(6).tolist()
        tables.append(
            [
                (r.index, r.seed, slot[r.expert_episode_id], r.success, r.failure_stage, plans[r.rollout_id])
                for r in report.rows
            ]
        )
    assert tables[0] == tables[1]
    assert len({row[2] for row in tables[0]}) > 1, "the rollouts imitate more than one demonstration"
