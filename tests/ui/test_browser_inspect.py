"""The Inspect tab in a real browser (Debian's headless Chromium driven by Playwright): replay a stored failed
rollout, fork it and correct it by dragging (losing nothing when the sim worker dies mid-fork), and say so when a
rollout's scene no longer loads. The store starts with one failed rollout (``browser_stores``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_stores import training_episodes_and_a_failed_rollout

# Tests that share the app are slow one by one (marked); the fast ones stay in `-m "not slow"` runs.
pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return training_episodes_and_a_failed_rollout(tmp_path_factory.mktemp("studio") / "data")


@pytest.mark.slow
def test_inspector_replays_a_stored_failed_rollout(studio, page, shots):
    tab = ui.tab(studio)
    ins = tab.inspector
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    first = ui.wait(
        lambda: ins.rollout.options[0] if "✘" in ins.rollout.options[0] else None, 10, "failures listed"
    )
    assert all("✘" in o for o in ins.rollout.options), "only failures"
    ins.checkpoint.value = "fixture-run/best"
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")
    first = ins.rollout.options[0]
    assert first.startswith(failed[0].id) and failed[0].failure_stage in first
    ui.click_and_see(page, page.get_by_role("button", name="Open", exact=True).first, "Stages:")
    assert tab.mode == "replay"
    steps = ins.replay.num_steps
    ins.timeline.slider.value = steps // 2
    ui.wait(lambda: f"Step {steps // 2} of" in ins.plan_info.content, 30, "the timeline to move")
    ui.wait(
        lambda: "predicted latent state" in ins.plan_info.content, 20, "a predicted image beside the frame"
    )
    ui.shot(page, shots / "inspect.png")
    mid = ins.replay.poses_at(steps // 2)
    assert not np.allclose(mid, ins.replay.poses_at(0)), "the scene moves along the timeline"
    assert "plan" in tab.view._overlays
    assert ins.n_plans == 1  # the stored null plan is not counted as a plan of its own
    assert "null plan" in tab.view._overlays, "a guided rollout shows its plan from the scene alone"
    assert (
        "guidance 3 moved the plan up to 0.12 m from it (demonstration gain 1.600; surprise 8.73)"
        in ins.plan_info.content
    )


@pytest.mark.slow
def test_fork_a_failed_rollout_correct_it_and_lose_nothing_when_the_worker_dies(studio, page, shots):
    """Inspect → fork the failed rollout before its misaimed grasp → drag the correction; the sim worker is killed
    while the bar is held; the recording continues on the restarted worker → saved, linked to the rollout."""
    import signal

    from studio.data.forks import fork_source
    from studio.sim.env import SimEnv
    from studio.sim.experts import expert_waypoints

    tab = ui.tab(studio)
    ins, tp = tab.inspector, tab.teleop
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")[0]
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    ins.checkpoint.value = "fixture-run/best"
    ui.wait(lambda: ins.rollout.options[0].startswith(failed.id), 10, "the failed rollout listed")
    shown = (
        ins.replay
    )  # an earlier test may have opened it: wait for this Open's replay (it resets the timeline)
    ui.click_and_wait(
        page.get_by_role("button", name="Open", exact=True).first,
        lambda: ui.wait(lambda: ins.replay is not shown and ins.record.id == failed.id, 90, "the replay"),
    )
    # A click repeated because the first open was slow opens the rollout again later, resetting the timeline to
    # step 0: wait until no open is queued before moving it.
    ui.wait(lambda: "opening the rollout" not in tab.actions, 120, "every queued Open", lambda: tab.actions)
    page.get_by_text("No episode was forked from this rollout yet").filter(visible=True).first.wait_for(
        timeout=30_000
    )
    k = 40  # the arm is on its way to the misaimed grasp
    ins.timeline.slider.value = k
    ui.wait(lambda: f"Step {k} of" in ins.plan_info.content, 30, "the timeline to move")
    before = {m.id for m in studio.store.episodes()}
    assert "opening the rollout" not in tab.actions and f"Step {k} of" in ins.plan_info.content
    ui.click_and_see(page, page.get_by_role("button", name="Fork at this step"), "Recording the fork")
    ui.wait(
        lambda: tp._recording and tab.mode == "teleop" and tp.info.robot == "panda",
        60,
        "the fork session",
        lambda: ui.teleop_state(tab),
    )
    assert (tp.info.task, tp.info.seed) == (failed.task, failed.seed)
    # A pose of the forked session. Nothing commands the arm yet, so from the restored tick it moves as the
    # rollout's physics state carries it (the arm was moving at tick k): exactly as a local restore stepped on
    # with the target held, however many ticks the session ran before this pose was seen.
    first = tp.client.poses.wait_until(lambda f: f.body_count == len(tp.info.body_names) and f.step >= k, 10)
    assert first is not None, f"no pose of the forked scene; {ui.teleop_state(tab)}"
    src = studio.store.catalog.get_rollout(failed.id)
    fs = fork_source(studio.store, src.id, k)
    with SimEnv("pick_place", "panda", control_dt=fs.control_dt) as env:
        env.restore(fs.task, fs.seed, fs.states, fs.gripper)
        # The arm the replay showed at tick k (it moves under a millimetre a tick).
        np.testing.assert_allclose(env.ee_pos, ins.replay.arrays["ee_pos_world"][k], atol=2e-3)
        for _ in range(first.step - k):
            env.step(env.target, env.gripper_cmd)
        np.testing.assert_allclose(
            first.ee_pos, env.ee_pos, atol=1e-6, err_msg=f"step {first.step}; {ui.teleop_state(tab)}"
        )
    ui.shot(page, shots / "fork-restored.png")

    # The correction a person would drag: above the bar, down, grasp, up, over the blue target, down, release.
    with SimEnv("pick_place", "panda") as env:
        env.restore(fs.task, fs.seed, fs.states, fs.gripper)
        grasp, lift, carry, place, _ = expert_waypoints(env)

    def drag(goal, seconds: float = 1.5) -> None:
        """The gizmo dragged to ``goal``: it moves, and its callback sends each position (latest wins)."""
        start = np.asarray(tp.client.latest_pose().ee_pos)
        n = int(seconds * 60)
        version = tp.client.poses.get()[1]
        for i in range(1, n + 1):  # one target per pose frame of the simulation
            p = start + (np.asarray(goal) - start) * i / n
            tp.gizmo.position = p
            tp.move_to(p)
            version = ui.next_pose(tp.client, version)
        ui.wait(
            lambda: np.linalg.norm(np.asarray(tp.client.latest_pose().ee_pos) - goal) < 0.01,
            20,
            f"the arm to reach {np.round(goal, 3)}",
            lambda: ui.teleop_state(tab),
        )

    drag(grasp[:3] + np.array([0.0, 0.0, 0.1]))
    drag(grasp[:3], 1.0)
    ui.click(page.get_by_role("button", name="Close", exact=True))
    ui.wait(lambda: tp.client.latest_pose().gripper == 1.0, 10, "the gripper to close")
    ui.sim_ticks(tp.client, 40)  # the fingers close on the bar
    drag(lift[:3])
    # The recording gains a tick with every control tick: its length is the pose's step plus a fixed offset (read
    # from one state message, which carries both, as the states are re-published only twice a second).
    dying = tp.client
    state = dying.state.wait_until(lambda s: s.recorded_steps > 0, 10)
    offset = state.recorded_steps - state.step
    # The sim worker dies while the bar is held.
    (sim,) = [p for p in studio.embedded.processes if p.kind == "sim"]
    sim.process.send_signal(signal.SIGKILL)
    ui.wait(
        lambda: "The sim worker was lost mid-recording" in tp.status.content or tp.client is None,
        60,
        "the loss to be noticed",
        lambda: ui.teleop_state(tab),
    )
    held_steps = dying.latest_pose().step + offset  # recorded when the worker's last pose left it
    ui.wait(
        lambda: (
            tp._recording
            and tp.client is not None
            and tp.client.worker != sim.worker
            and tp.status.content.startswith("Continuing the interrupted recording")
        ),
        180,
        "the recording to continue on the restarted worker",
        lambda: ui.teleop_state(tab),
    )
    resumed = tp.client.state.wait_until(lambda s: s.recorded_steps > 0, 10).recorded_steps
    # Draft chunks leave every 0.1 s (5 ticks): at most that and the chunk in flight are lost. The other way, the
    # last chunk that arrived can hold ticks whose pose frames the kill dropped in flight (a fresh clone's run kept
    # 2 ticks more than the last pose seen), at most one chunk's worth.
    assert held_steps - 10 <= resumed <= held_steps + 5, (held_steps, resumed)
    # The restarted worker's session state can arrive before its first pose frame.
    pose = tp.client.poses.wait_until(lambda f: True, 10)
    assert pose is not None, f"no pose from the restarted worker; {ui.teleop_state(tab)}"
    assert np.linalg.norm(np.asarray(pose.ee_pos) - lift[:3]) < 0.02, (
        "the arm is where it was when its worker died"
    )
    ui.open_tab(page, "Inspect", "Recording the fork")
    ui.shot(page, shots / "fork-resumed.png", scroll_to="Fork from this moment")
    drag(carry[:3], 2.0)
    drag(place[:3], 1.0)
    ui.click(page.get_by_role("button", name="Open", exact=True).last)
    ui.wait(lambda: tp.client.latest_pose().gripper == 0.0, 10, "the gripper to open")
    ui.sim_ticks(tp.client, 50)  # the fingers let the bar go
    drag(place[:3] + np.array([0.0, 0.0, 0.08]))
    ui.wait(
        lambda: tp.success.value, 10, "the task's check to see the bar placed", lambda: ui.teleop_state(tab)
    )
    ui.click_and_wait(
        page.get_by_role("button", name="Stop & save the fork"),
        lambda: ui.wait(
            lambda: tp.status.content.startswith("Saved"),
            120,
            "the fork to be stored",
            lambda: ui.teleop_state(tab),
        ),
    )
    (new,) = [m for m in studio.store.episodes() if m.id not in before]
    assert new.extra["forked_from"] == {"rollout": failed.id, "step": k, "episode": failed.episode_id}
    assert (new.role, new.embodiment, new.task, new.seed, new.success) == (
        "agent",
        "panda",
        failed.task,
        failed.seed,
        True,
    )
    _, _, arrays = studio.store.load_arrays(new.id)
    _, _, rolled = studio.store.load_arrays(failed.episode_id)
    np.testing.assert_array_equal(arrays["qpos"][: k + 1], rolled["qpos"][: k + 1])
    assert np.all(np.diff(arrays["time"]) > 0) and new.num_steps > resumed
    assert studio.drafts.drafts() == [], "the stored episode replaced its draft"
    ui.wait(lambda: f"`{new.id}` (agent, from step {k}, ✔)" in ins.fork_status.content, 20, "the fork listed")
    ui.shot(page, shots / "fork-saved.png")


@pytest.mark.slow
def test_a_rollout_whose_scene_no_longer_loads_says_so(studio, page, shots, monkeypatch):
    import studio.sim.scenes as scenes
    from studio.data.forks import STATES_FILE

    tab = ui.tab(studio)
    ins, tp = tab.inspector, tab.teleop
    failed = studio.store.catalog.rollouts(success=False, checkpoint_id="fixture-run/best")[0]
    ui.open_tab(page, "Inspect", "Every rollout")
    ins.outcome.value = "failures"
    ins.checkpoint.value = "fixture-run/best"
    ui.wait(lambda: ins.rollout.options[0].startswith(failed.id), 10, "the failed rollout listed")

    def gone(*args, **kwargs):
        raise FileNotFoundError("scenes/pick_place.xml was removed")

    with monkeypatch.context() as m:  # the scene file is gone: replaying needs it
        m.setattr(scenes, "build_model", gone)
        ui.click(page.get_by_role("button", name="Open", exact=True).first)
        page.get_by_text("cannot be replayed: its scene does not load here").filter(
            visible=True
        ).first.wait_for(timeout=60_000)
    ui.shot(page, shots / "inspect-scene-gone.png")
    # The scene loads again, but its model changed since the rollout: the fork is refused with the reason.
    ui.click_and_see(page, page.get_by_role("button", name="Open", exact=True).first, "Stages:")
    path = Path(failed.path) / STATES_FILE
    kept = path.read_bytes()
    try:
        with np.load(path) as data:
            np.savez_compressed(path, states=data["states"][:, :-2])
        ui.click(page.get_by_role("button", name="Fork at this step"))
        page.get_by_text("the scene changed since the episode was recorded").filter(
            visible=True
        ).first.wait_for(timeout=60_000)
    finally:
        path.write_bytes(kept)
    assert not tp._recording and studio.drafts.drafts() == [], "a refused fork leaves nothing behind"
    ui.shot(page, shots / "fork-refused.png")
