"""The policies shipped in ``studio/policies``: small enough, with their decoders, each planning a held-out task of
the scene it was trained on (pick-and-place, push or Meta-World) from a demonstration by the demonstrator it learnt
from (the Sawyer, the simulated human hand or the Panda)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from studio.cli import main
from studio.data.paths import SHIPPED_POLICY_DIR
from studio.data.splits import load_split
from studio.data.store import EpisodeStore
from studio.model.checkpoint_info import checkpoint_scene
from studio.sim.env import WORKSPACE
from studio.sim.recording import robot_of
from studio.ui.runs import RunRegistry

torch.set_num_threads(1)
POLICIES = sorted(f for f in SHIPPED_POLICY_DIR.glob("*.pt") if not f.name.endswith(".decoder.pt"))
PICK_PLACE = [p for p in POLICIES if checkpoint_scene(p) == "pick_place"]
PUSH = [p for p in POLICIES if checkpoint_scene(p) == "push"]
METAWORLD = [p for p in POLICIES if checkpoint_scene(p) == "metaworld"]
#: Who demonstrated each policy's training pairs (its file's configuration, else its JSON file).
DEMONSTRATORS = {
    c.path: c.demonstrators for c in RunRegistry("unused", policy_dir=SHIPPED_POLICY_DIR).default_policies()
}


#: Of the twenty button-press rollouts (seeds 300-319, drawing on ten demonstrations) of the Meta-World policy (11
#: succeed; 12 for the policy shipped before it). Which demonstration and which scenes move it a lot: one
#: demonstration alone gave 5 to 10 of ten scenes, and 100 rollouts on 20 demonstrations gave 80 % for both
#: policies. The bound, eight of twenty, leaves room for that spread.
MIN_BUTTON_PRESSES = 8


def demonstrator_args(policy) -> list[str]:
    """``studio collect`` arguments that record a demonstration by the demonstrator ``policy`` learnt from."""
    (embodiment,) = DEMONSTRATORS[str(policy)] or ("sawyer",)
    robot = robot_of(embodiment)
    return ["--robot", robot] + (["--role", "expert"] if robot == "panda" else [])


def test_a_policy_ships_with_its_decoder_and_within_the_size_limit():
    assert POLICIES, f"no policy in {SHIPPED_POLICY_DIR}"
    for policy in POLICIES:
        assert policy.stat().st_size <= 25 * 2**20, f"{policy.name} is over 25 MB"
        assert policy.with_name(f"{policy.stem}.decoder.pt").is_file(), f"{policy.name} has no latent decoder"
        assert policy.with_suffix(".json").is_file(), (
            f"{policy.name} has no JSON file with its measured results"
        )
    assert PICK_PLACE and PUSH and METAWORLD, "a pick-and-place, a push and a Meta-World policy ship"
    assert len(PICK_PLACE) + len(PUSH) + len(METAWORLD) == len(POLICIES), (
        "every shipped policy names its scene (by its tasks)"
    )
    for policy in POLICIES:
        assert len(DEMONSTRATORS[str(policy)]) == 1, f"{policy.name} does not say who demonstrated to it"


@pytest.fixture(scope="module")
def demos_by(tmp_path_factory):
    """One scripted demonstration of each held-out pick-and-place task by the demonstrator a policy learnt from,
    collected as a user would (once per demonstrator)."""
    collected: dict[tuple[str, ...], dict[str, np.ndarray]] = {}

    def demos(policy) -> dict[str, np.ndarray]:
        args = demonstrator_args(policy)
        if tuple(args) not in collected:
            root = tmp_path_factory.mktemp("store")
            tasks = list(load_split("pick_place").test)
            assert (
                main(
                    [
                        "collect",
                        *args,
                        "--tasks",
                        *tasks,
                        "--episodes",
                        "1",
                        "--seed",
                        "5",
                        "--data-dir",
                        str(root),
                        "--no-progress",
                    ]
                )
                == 0
            )
            with EpisodeStore(root) as store:
                collected[tuple(args)] = {t: store.load_frames(store.episodes(task=t)[0].id) for t in tasks}
        return collected[tuple(args)]

    return demos


@pytest.mark.parametrize("policy", PICK_PLACE, ids=lambda p: p.stem)
def test_the_shipped_policy_plans_a_held_out_task(policy, demos_by):
    from studio.model.planner import Planner
    from studio.sim.env import SimEnv
    from studio.sim.waypoints import gripper_flags

    demos = demos_by(policy)
    planner = Planner.load(policy)
    releases = []
    with SimEnv("pick_place", "panda") as env:
        for i, (task, frames) in enumerate(sorted(demos.items())):
            env.reset(task, seed=100 + i)
            cam = env.camera_model()
            res = planner.plan(frames, env.render(), cam.K, cam.T_world_cam)
            wps = res.waypoints_world
            assert wps.shape == (5, 4) and np.isfinite(wps).all()
            assert (wps[:, :3] > WORKSPACE[0] - 0.1).all() and (wps[:, :3] < WORKSPACE[1] + 0.1).all(), wps
            flags = gripper_flags(wps)
            assert flags.any(), "the plan never closes the gripper"
            last_closed = np.flatnonzero(flags)[-1]
            releases.append(wps[min(last_closed + 1, 4), :2])  # where the gripper opens again
            assert res.latent_states.shape[0] > 0 and np.isfinite(res.pooled_states).all()
    # the two held-out tasks put the bar in different zones (14 cm apart): the plans follow their demonstrations
    assert np.linalg.norm(releases[0] - releases[1]) > 0.05, releases


@pytest.mark.parametrize("policy", PICK_PLACE, ids=lambda p: p.stem)
def test_the_shipped_policy_grasps_the_demonstrated_object_wherever_it_lies(policy, demos_by):
    """Objects are shuffled in every scene, so one demonstration must lead to different grasp points in different
    scenes: the nearest object to the grasp is the demonstrated one (chance: one in four), not whatever lies where
    the demonstration grasped."""
    from studio.bench.plan import grasp_and_release, task_object
    from studio.model.planner import Planner
    from studio.sim.env import SimEnv

    demos = demos_by(policy)
    planner = Planner.load(policy)
    picked, grasps = [], []
    with SimEnv("pick_place", "panda") as env:
        for task, frames in sorted(demos.items()):
            for seed in range(200, 204):
                env.reset(task, seed=seed)
                cam = env.camera_model()
                plan = planner.plan(frames, env.render(), cam.K, cam.T_world_cam)
                grasp, _ = grasp_and_release(plan.waypoints_world)
                assert grasp is not None, f"{task}, seed {seed}: the plan never closes the gripper"
                poses = env.object_poses()
                nearest = min(poses, key=lambda o: np.linalg.norm(poses[o][:2] - grasp))
                picked.append(nearest == task_object(task))
                grasps.append(grasp)
    assert sum(picked) >= 6, f"the demonstrated object was picked in {sum(picked)} of {len(picked)} scenes"
    assert np.ptp(np.array(grasps)[:, 0]) > 0.1, "the grasp point does not move with the scene"


@pytest.mark.parametrize("policy", PUSH, ids=lambda p: p.stem)
def test_the_shipped_push_policy_pushes_the_demonstrated_box_backward(policy, tmp_path):
    """The unseen push task (blue box, backward) from one scripted demonstration by the policy's demonstrator: in
    every scene (the boxes swap slots) the push starts behind the blue box, not the red one, and moves it towards
    the robot (-y)."""
    from studio.model.planner import Planner
    from studio.sim.env import SimEnv

    (task,) = load_split("push").test
    assert task == "push/blue-backward"
    assert (
        main(
            [
                "collect",
                "--scene",
                "push",
                *demonstrator_args(policy),
                "--tasks",
                task,
                "--episodes",
                "10",
                "--seed",
                "5",
                "--data-dir",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    with EpisodeStore(tmp_path) as store:
        frames = store.load_frames(store.episodes(task=task)[0].id)
    planner = Planner.load(policy)
    assert {t.split("/")[0] for t in planner.tasks} == {"push"} and task not in planner.tasks, (
        "never trained on it"
    )
    slots = set()
    with SimEnv("push", "panda") as env:
        for seed in range(200, 206):
            env.reset(task, seed=seed)
            cam = env.camera_model()
            wps = planner.plan(frames, env.render(), cam.K, cam.T_world_cam).waypoints_world
            assert wps.shape == (5, 4) and np.isfinite(wps).all()
            poses = env.object_poses()
            slots.add(poses["blue"][0] > poses["red"][0])
            start = wps[1, :2]  # down behind the box
            nearest = min(poses, key=lambda o: abs(poses[o][0] - start[0]))
            assert nearest == "blue", f"seed {seed}: the push starts at x={start[0]:.3f}, boxes {poses}"
            assert wps[2, 1] - start[1] < -0.1, f"seed {seed}: not a backward push: {wps[:, :3]}"
    assert slots == {True, False}, "both slot orders were planned"


@pytest.mark.parametrize("policy", METAWORLD, ids=lambda p: p.stem)
def test_the_shipped_metaworld_policy_presses_the_held_out_button(policy, tmp_path):
    """button-press, one of the four tasks held out of the 46 training tasks, from ten scripted demonstrations, run
    as ``studio eval`` runs it (Sawyer, no re-plans): the button is pressed in a good part of twenty scenes."""
    from studio.eval.evaluation import evaluate
    from studio.model.planner import Planner

    task = "metaworld/button-press-v3"
    assert task in load_split("metaworld").test and task not in Planner.load(policy).tasks, (
        "never trained on it"
    )
    assert (
        main(
            [
                "collect",
                "--scene",
                "metaworld",
                "--robot",
                "sawyer",
                "--tasks",
                task,
                "--episodes",
                "10",
                "--seed",
                "5",
                "--data-dir",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    report = evaluate(str(policy), [task], 20, 300, replan=0, data_dir=tmp_path, progress=False)
    assert len({row.expert_episode_id for row in report.rows}) > 5, "many demonstrations are imitated"
    outcomes = [row.success for row in report.rows]
    assert len(outcomes) == 20 and sum(outcomes) >= MIN_BUTTON_PRESSES, outcomes
