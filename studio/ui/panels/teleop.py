"""Teleop & record: one teleop session per tab on a sim worker, driven by a gizmo, recorded into the store.

The session is a :class:`~studio.backend.teleop_client.TeleopClient`: the gizmo's drags become
end-effector targets (latest wins; IK runs on the worker), the worker streams body poses back at its
control rate and camera images at a few hertz. Recording, stopping (with the user's success verdict,
pre-filled from the task's predicate) and discarding are requests to the session; the worker stores the
episode and reports where it went.

Every recording is journaled as a draft (``<data-dir>/drafts``, :mod:`studio.backend.forking`) while it
runs. If the sim worker dies mid-recording, the panel reopens the session on the next sim worker as a
continuation of the draft, still recording; a draft left by a studio that stopped can be resumed or dropped
from *Interrupted recordings*. A rollout forked in *Inspect* arrives here the same way: the session
continues it from the chosen tick and is recording.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.forking import Continuation, DraftKeeper, new_draft_id, resume_draft
from studio.backend.recording_sink import DEFAULT_ROLE
from studio.backend.teleop_client import TeleopClient, choose_sim_worker
from studio.data.drafts import DraftError
from studio.data.splits import load_split
from studio.sim.tasks import list_tasks
from studio.ui.reach import (
    NUDGE_STEPS,
    PATH_HZ,
    HeightRules,
    SceneModel,
    clip_to_workspace,
    down_height,
    object_label,
    path_targets,
)
from studio.ui.teleop_cues import DepthCues, describe

log = logging.getLogger("studio.ui")

HINTS = """**Click** an object or the table in the 3D view to move the gripper over it (at its height), then
**Down** / **Up**, *Close* / *Open*; nudge by a step or use the keys (arrows, PgUp/PgDn, D/U, C/O) for the last
centimetres; or **drag the gizmo** at the gripper (IK runs on the sim worker). **Record** resets the scene to its seed and starts an episode;
**Stop & save** stores it (success is pre-filled by the task's check — override it if you disagree);
**Discard** drops it. Sawyer and human-hand recordings are expert demonstrations (the hand's stored as
`human`; it grasps by pinching an object between thumb and index), Panda recordings agent trajectories."""

SCENES = ("pick_place", "push", "metaworld")
#: Robots of the tabletop scenes (Meta-World has the Sawyer only).
TABLETOP_ROBOTS = ("sawyer", "panda", "hand")
PREVIEW_HZ = 5.0
#: The camera frustum in the 3D view shows the live image this often; the panel's preview (PREVIEW_HZ) is the
#: live view. Each new frustum image is a new WebGL texture and opens a settle window of redraws: without a GPU
#: (Chromium on llvmpipe, a still scene) 5 Hz kept the browser at 174 % of a core, 1 Hz at 128 %, 0.2 Hz at 44 %
#: (13–50 % with no image updates); docs/ui.md.
FRUSTUM_IMAGE_HZ = 0.2
PREVIEW_SIZE = (120, 160)
#: Depth cues and the distance line are redrawn this often while the live session is shown.
CUES_HZ = 5.0
#: Gizmo size (metres) and handle width (pixels): large enough to grab without orbiting the camera by mistake.
GIZMO_SCALE = 0.15
GIZMO_LINE_WIDTH = 6.0
#: Keyboard shortcuts (viser command hotkeys): nudges along the axes, Down / Up, Close / Open.
HOTKEYS = {
    "arrowleft": ("nudge", (-1, 0, 0)),
    "arrowright": ("nudge", (1, 0, 0)),
    "arrowdown": ("nudge", (0, -1, 0)),
    "arrowup": ("nudge", (0, 1, 0)),
    "pagedown": ("nudge", (0, 0, -1)),
    "pageup": ("nudge", (0, 0, 1)),
    "D": ("down", None),
    "U": ("up", None),
    "C": ("close", None),
    "O": ("open", None),
}
#: The tab action that shows the live session (``StudioTab.run``'s name for it; queued once at a time).
SHOW_LIVE = "showing the teleop scene"


def scene_tasks(scene: str) -> list[str]:
    return list_tasks(scene)


def held_out_note(task: str) -> str:
    """A line under the task choice when ``task`` is held out of training in its scene's split."""
    try:
        held = task in load_split(task.split("/")[0]).test
    except (FileNotFoundError, ValueError, KeyError):
        return ""
    return (
        f"`{task}` is **held out**: the policies never train on it — a demonstration of it is for *Imitate*."
        if held
        else ""
    )


class TeleopPanel:
    """The *Teleop* tab of one browser tab."""

    def __init__(self, tab):
        self.tab = tab
        self.app = tab.app
        self.client: TeleopClient | None = None
        self.info: msg.SessionInfo | None = None
        self.gizmo = None
        self._geometry_key: tuple | None = None
        self._gripper = 0.0
        self._pending: dict[int, float] = {}
        self._pending_lock = threading.Lock()
        self._success_touched = False
        self._success_written = False  # the value the task's check last wrote into the box
        self._recording = False
        self._closed = False
        self._token = 0
        self.drags = 0
        self._lost = False
        self._draft: str | None = None  # the draft of the recording in progress
        self._resume: str | None = None  # a draft to continue when the session is (re)opened
        self._fork_note = ""  # what the recording in progress continues, for the status line
        self._fork_origin: dict = {}  # the rollout (and step) the recording in progress was forked from
        self.keeper = DraftKeeper(self.app.drafts)
        self._streaming = False
        self._scene_model: SceneModel | None = None
        self._rules: HeightRules | None = None
        self._poses: np.ndarray | None = None
        self._rest_pending = True
        self._target: np.ndarray | None = None  # the newest end-effector target sent
        self._path_gen = 0
        self._goal: np.ndarray | None = None  # where the newest click / height / nudge motion goes
        self._path_lock = threading.Lock()
        self.clicks = 0
        self.cues = DepthCues(tab.client.scene)
        gui = tab.client.gui
        gui.add_markdown(HINTS)
        scenes = tuple(s for s in SCENES if scene_tasks(s))
        self.scene = gui.add_dropdown("Scene", scenes, initial_value=scenes[0])
        self.robot = gui.add_dropdown(
            "Robot",
            TABLETOP_ROBOTS,
            initial_value="sawyer",
            hint="Sawyer or a human hand: expert demonstrations; Franka Panda: agent trajectories",
        )
        tasks = scene_tasks(scenes[0])
        self.task = gui.add_dropdown("Task", tuple(tasks), initial_value=tasks[0])
        self.task_note = gui.add_markdown(held_out_note(tasks[0]))
        self.seed = gui.add_number(
            "Seed", initial_value=0, min=0, step=1, hint="same seed, same initial scene"
        )
        self.scene_buttons = gui.add_button_group("Scene state", ("New seed", "Reset"))
        self.grip = gui.add_button_group("Gripper", ("Open", "Close"))
        with gui.add_folder("Move by clicking"):
            self.click_mode = gui.add_checkbox(
                "Click to move",
                initial_value=True,
                hint="a click on an object or the table moves the gripper over it, keeping its height",
            )
            self.height = gui.add_button_group("Height", ("Down", "Up"))
            self.nudge_step = gui.add_dropdown("Nudge step", tuple(NUDGE_STEPS), initial_value="1 cm")
            self.nudge_x = gui.add_button_group("Nudge x", ("−x", "+x"))
            self.nudge_y = gui.add_button_group("Nudge y", ("−y", "+y"))
            self.nudge_z = gui.add_button_group("Nudge z", ("−z", "+z"))
        self.rec_status = gui.add_markdown("")
        self.status = gui.add_markdown("Waiting for a sim worker…")
        self.cue_line = gui.add_markdown("")
        self.record = gui.add_button(
            "Record",
            color="red",
            icon="player-record",
            hint="reset the scene to its seed and start recording",
        )
        self.stop = gui.add_button("Stop & save", icon="player-stop", disabled=True)
        self.discard = gui.add_button("Discard", icon="x", disabled=True)
        self.success = gui.add_checkbox(
            "Success",
            initial_value=False,
            hint="pre-filled by the task's success check; tick or untick to override",
        )
        self.preview = gui.add_image(np.zeros((*PREVIEW_SIZE, 3), np.uint8), label="External camera (live)")
        with gui.add_folder(
            "Interrupted recordings", expand_by_default=True, visible=False
        ) as self.drafts_folder:
            self.draft_list = gui.add_dropdown("Draft", ("(none)",))
            self.draft_buttons = gui.add_button_group("Draft action", ("Resume", "Drop"))
        with gui.add_folder("Episodes of this task", expand_by_default=False):
            self.episode_list = gui.add_dropdown("Episode", ("(none)",))
            self.delete_selected = gui.add_button("Delete selected episode…", icon="trash")
            self.delete_last = gui.add_button("Delete my last recording…", icon="trash")
        self._list_version = -1
        self._list_task = ""

        self.scene.on_update(self._on_scene)
        self.robot.on_update(lambda e: e.client and tab.run(self.open, "opening the session"))
        self.task.on_update(self._on_task)
        self.seed.on_update(lambda e: e.client and tab.run(self.reset, "resetting the scene"))
        self.scene_buttons.on_click(self._on_scene_button)
        self.grip.on_click(lambda e: self.set_gripper(1.0 if e.target.value == "Close" else 0.0))
        self.height.on_click(lambda e: self.move_height(e.target.value))
        self.nudge_x.on_click(lambda e: self.nudge((1.0 if e.target.value == "+x" else -1.0, 0.0, 0.0)))
        self.nudge_y.on_click(lambda e: self.nudge((0.0, 1.0 if e.target.value == "+y" else -1.0, 0.0)))
        self.nudge_z.on_click(lambda e: self.nudge((0.0, 0.0, 1.0 if e.target.value == "+z" else -1.0)))
        tab.client.scene.on_click()(self._on_scene_click)
        for key, (what, axis) in HOTKEYS.items():
            command = tab.client.gui.add_command(f"Teleop: {what} {axis or ''}".strip(), hotkey=key)
            command.on_trigger(lambda _e, what=what, axis=axis: self._on_hotkey(what, axis))
        self.record.on_click(lambda _: tab.run(self.start_recording, "starting the recording"))
        self.stop.on_click(lambda _: tab.run(self.stop_and_save, "saving the episode"))
        self.discard.on_click(lambda _: tab.run(self.discard_recording, "discarding the recording"))
        self.success.on_update(self._on_success)
        self.delete_selected.on_click(lambda _: self._confirm_delete(selected=True))
        self.delete_last.on_click(lambda _: self._confirm_delete(selected=False))
        self.draft_buttons.on_click(self._on_draft_button)
        self._drafts_shown: tuple = ()
        self._preview_thread = threading.Thread(target=self._preview_loop, daemon=True, name="teleop-preview")
        self._cues_thread = threading.Thread(target=self._cues_loop, daemon=True, name="teleop-cues")

    # ------------------------------------------------------------------ what the panel shows, read-only
    @property
    def recording(self) -> bool:
        return self._recording

    @property
    def rest_known(self) -> bool:
        """Whether the objects' rest heights of the current episode are known (Down's place height)."""
        return not self._rest_pending

    @property
    def scene_model(self) -> SceneModel | None:
        return self._scene_model

    @property
    def latest_poses(self) -> np.ndarray | None:
        return self._poses

    @property
    def motion(self) -> tuple[int, np.ndarray | None]:
        """The newest click, Down/Up or nudge motion: its number (0: none yet) and where it goes."""
        return self._path_gen, None if self._goal is None else self._goal.copy()

    @property
    def target(self) -> np.ndarray | None:
        """The newest end-effector target sent to the session."""
        return None if self._target is None else self._target.copy()

    # ------------------------------------------------------------------ session
    def start(self) -> None:
        self._preview_thread.start()
        self._cues_thread.start()
        self._await_worker()

    def _await_worker(self) -> None:
        """Open the session once a sim worker is on the bus (on its own thread: other panels stay usable)."""

        def wait() -> None:
            directory = self.app.hub.directory
            while not self._closed:
                try:
                    choose_sim_worker(directory)
                    break
                except bus.BusError:
                    self.status.content = (
                        "Waiting for a sim worker to join (`studio worker sim --connect …`)…"
                    )
                    directory.wait_for(lambda ws: any(w.kind == "sim" and w.status for w in ws), 1.0)
            if not self._closed:
                self.tab.run(self.open, "opening the teleop session")

        threading.Thread(target=wait, daemon=True, name="teleop-wait-worker").start()

    def open(self) -> None:
        """(Re-)open the session with the chosen scene, robot, task and seed."""
        if self.client is None:
            worker = choose_sim_worker(self.app.hub.directory)
            self.client = TeleopClient(
                self.app.hub.session, worker, on_pose=self._on_pose, on_draft=self.keeper, timeout=10.0
            )
        if self._resume is not None:
            draft, self._resume = self._resume, None
            return self.resume(draft)
        scene, robot, task, seed = self.scene.value, self.robot.value, self.task.value, int(self.seed.value)
        self.status.content = f"Opening **{task}** with the **{robot}** on `{self.client.worker}`…"
        if self.info is not None and (self.info.scene, self.info.robot) != (scene, robot):
            # The last session's picture is another scene: blank until the new session's first frame.
            self.preview.image = np.zeros((*PREVIEW_SIZE, 3), np.uint8)
        self.info = self.client.open(scene, robot, task, seed)
        self._rest_pending, self._target, self._goal = True, None, None
        self._gripper = 0.0  # a reset scene's gripper is open
        self._recording = False
        self._set_recording_ui(False)
        self._streaming = False  # a (re-)opened session streams nothing until the live view asks
        self.show_live()
        self.status.content = (
            f"**{task}** with the **{robot}**, seed {seed} — ready. Drag the gizmo or click an object."
        )

    # ------------------------------------------------------------------ continuing episodes
    def continue_episode(self, go: Continuation, what: str) -> None:
        """Open the session as a continuation of a recorded episode (a fork or a draft), recording on."""
        if self.client is None:
            worker = choose_sim_worker(self.app.hub.directory)
            self.client = TeleopClient(
                self.app.hub.session, worker, on_pose=self._on_pose, on_draft=self.keeper, timeout=10.0
            )
        if self._recording:
            self._drop_draft()
            self.tab.notify(
                "Recording discarded", "Continuing another episode discarded the unsaved recording."
            )
        self.status.content = f"Restoring {what} on `{self.client.worker}`…"
        self.info = self.client.open(go.scene, go.robot, go.task, go.seed, fork=go.fork)
        self._gripper = float(go.fork.gripper)  # drags keep the episode's gripper (closed on a carry)
        self._rest_pending, self._target, self._goal = True, None, None
        # Show what the session is (these widgets only reopen the session on a user's change).
        if self.scene.value != go.scene:
            self.scene.value = go.scene
            self.narrow_choices()
        self.robot.value, self.task.value, self.seed.value = go.robot, go.task, go.seed
        self._draft, self._fork_note, self._fork_origin = go.fork.draft, what, dict(go.fork.origin)
        self._recording = True
        self._success_touched = self._success_written = False
        self.success.value = False
        self._streaming = False
        self.show_live()
        self._set_recording_ui(True)
        self.status.content = (
            f"Continuing {what} — {go.steps} ticks restored exactly, recording. Drag the gizmo to correct, "
            "then **Stop & save** (or **Discard**)."
        )

    def is_recording_fork_of(self, rollout_id: str | None) -> bool:
        """Whether this tab is recording a continuation of rollout ``rollout_id``."""
        return rollout_id is not None and self._recording and self._fork_origin.get("rollout") == rollout_id

    def resume(self, draft_id: str) -> None:
        """Continue an interrupted recording from the last tick its draft holds."""
        try:
            go = resume_draft(self.app.store, self.app.drafts, draft_id)
        except (DraftError, ValueError) as e:
            self.tab.notify("Cannot resume the recording", str(e), error=True)
            self.status.content = f"**Cannot resume** draft `{draft_id}`: {e}"
            return self.open()
        origin = go.fork.origin
        what = f"the interrupted recording `{draft_id}`" + (
            f" (forked from rollout `{origin['rollout']}` at step {origin['step']})"
            if origin.get("rollout")
            else ""
        )
        self.continue_episode(go, what)

    def _drop_draft(self) -> None:
        if self._draft is not None:
            self.app.drafts.discard(self._draft)
        self._draft, self._fork_note, self._fork_origin = None, "", {}

    def _on_draft_button(self, event) -> None:
        draft = self.draft_list.value.split(" ")[0]
        if draft == "(none)":
            return
        if event.target.value == "Resume":
            self.tab.run(lambda: self.resume(draft), "resuming the recording")
        else:
            self.app.drafts.discard(draft)
            self._drafts_shown = ()
            self.tab.notify("Draft dropped", draft)

    def reset(self) -> None:
        if self.client is None or self.info is None:
            return self.open()
        task, seed = self.task.value, int(self.seed.value)
        if self._recording:
            self.tab.notify("Recording discarded", "Resetting the scene discarded the unsaved recording.")
        self.info = self.client.reset(task, seed)
        self._rest_pending, self._target, self._goal = True, None, None
        self._gripper = 0.0  # a reset scene's gripper is open
        if self._recording:
            self._drop_draft()
        self._recording = False
        self._set_recording_ui(False)
        self.show_live()
        self.status.content = f"**{task}** with the **{self.info.robot}**, seed {seed} — ready."

    def show_live(self) -> None:
        """Show the live session in the scene (fetching its geometry when the model changed)."""
        if self.client is None or self.info is None:
            return
        info = self.info
        key = ("teleop", info.scene, info.robot, info.body_names)
        if key != self._geometry_key or self.tab.view.key != key or self._scene_model is None:
            geometry = self.client.geometry()
            self.tab.view.load(geometry, key)
            self._geometry_key = key
            self._scene_model = SceneModel(geometry, info.robot)
            self._rules = HeightRules(info.robot)
        self._token = self.tab.set_mode("teleop")
        self.tab.view.set_camera(info.camera)
        _, version = self.client.poses.get()
        frame, _ = self.client.poses.wait_newer(version, 1.0)  # a pose of the scene as it is now
        if frame is not None:
            self.tab.push_poses(self._token, frame.poses_array())
            self._remember_rest(frame)
        self._place_gizmo(np.asarray(frame.ee_pos) if frame is not None else None)

    def _remember_rest(self, frame: msg.PoseFrame | None = None) -> None:
        """After a reset or restore, note where the objects rest (Down's place height), from a fresh pose."""
        if not self._rest_pending or self._scene_model is None or self._rules is None or self.client is None:
            return
        if frame is None:
            _, version = self.client.poses.get()
            frame, version = self.client.poses.wait_newer(version, 1.0)
            frame, _ = self.client.poses.wait_newer(version, 1.0)  # past a frame that was in flight
        if frame is not None:
            self._rules.remember_rest(
                self._scene_model.object_positions(frame.poses_array()), np.asarray(frame.ee_pos)
            )
            self._rest_pending = False

    def on_mode(self, mode: str) -> None:
        """The tab's scene changed what it shows: the gizmo and the camera stream only serve the live view."""
        live = mode == "teleop"
        if self.gizmo is not None:
            self.gizmo.visible = live
        if not live:
            self.cues.hide()
        client = self.client
        if client is not None and live != self._streaming:
            self._streaming = live
            try:
                client.stream_frames(PREVIEW_HZ if live else 0.0, quality=70)
            except bus.BusError:
                self._streaming = not live  # try again at the next switch

    def _place_gizmo(self, ee: np.ndarray | None) -> None:
        if ee is None:
            return
        if self.gizmo is None:
            self.gizmo = self.tab.client.scene.add_transform_controls(
                "/gizmo",
                scale=GIZMO_SCALE,
                disable_rotations=True,
                depth_test=False,
                line_width=GIZMO_LINE_WIDTH,
                position=ee,
            )
            self.gizmo.on_update(self._on_gizmo_event)
        else:
            self.gizmo.position = ee
        self.gizmo.visible = True

    # ------------------------------------------------------------------ commands
    def _on_gizmo_event(self, event) -> None:
        if event.client is not None:
            self.drags += 1
            self._path_gen += 1  # a drag takes over from a click's motion
            self._goal = None
        self.move_to(np.asarray(event.target.position, dtype=np.float64))

    def move_to(self, position: np.ndarray) -> int | None:
        """Send the end-effector target (the gizmo's callback; tests and the benchmark call it the same way)."""
        if self.client is None or self.info is None:
            return None
        received = time.perf_counter()
        if self.tab.mode != "teleop" and SHOW_LIVE not in self.tab.actions:
            self.tab.run(self.show_live, SHOW_LIVE)  # once, not once per drag event
        seq = self.client.set_target(position, self._gripper)
        self._target = np.asarray(position, dtype=np.float64)
        with self._pending_lock:
            self._pending[seq] = received
            if len(self._pending) > 1000:
                for old in sorted(self._pending)[:500]:
                    del self._pending[old]
        return seq

    def set_gripper(self, closed: float) -> None:
        self._gripper = float(closed)
        if self.client is None:
            return
        target = self._current_target()
        if target is not None:
            self.move_to(target)

    # ------------------------------------------------------------------ click to reach
    def _current_target(self) -> np.ndarray | None:
        """Where the arm is being sent: the newest target, else the gizmo, else the grasp point."""
        if self._target is not None:
            return self._target.copy()
        if self.gizmo is not None:
            return np.asarray(self.gizmo.position, dtype=np.float64)
        frame = self.client.latest_pose() if self.client is not None else None
        return np.asarray(frame.ee_pos, dtype=np.float64) if frame is not None else None

    def _motion_base(self) -> np.ndarray | None:
        """Where the next click, Down/Up or nudge starts from: the goal of the motion under way (so quick
        presses add up), else the newest target."""
        return self._goal.copy() if self._goal is not None else self._current_target()

    def reach(self, goal: np.ndarray) -> int:
        """Move the target to ``goal`` along a minimum-jerk path (replacing a path under way); returns its id."""
        start = self._current_target()
        if start is None or self.client is None:
            return -1
        goal = clip_to_workspace(goal)
        targets = path_targets(start, goal)
        with self._path_lock:
            self._path_gen += 1
            gen = self._path_gen
            self._goal = goal.copy()

        def run() -> None:
            period = 1.0 / PATH_HZ
            due = time.monotonic()
            for p in targets:
                if gen != self._path_gen or self._closed:
                    return
                try:
                    self.move_to(p)
                except bus.BusError:
                    return
                due += period
                time.sleep(max(0.0, due - time.monotonic()))
            if gen == self._path_gen and self.gizmo is not None:
                self.gizmo.position = goal

        threading.Thread(target=run, daemon=True, name="teleop-reach").start()
        return gen

    def _on_scene_click(self, event) -> None:
        """A click in the 3D view: move over what it hit (an object's centre, or the point on a surface)."""
        model, poses = self._scene_model, self._poses
        if not self.click_mode.value or self.tab.mode != "teleop" or model is None or poses is None:
            return
        hit = model.cast(poses, event.ray_origin, event.ray_direction)
        if hit is None:
            self.status.content = "That click hit nothing in the scene: click an object or the table."
            return
        start = self._motion_base()
        if start is None:
            return
        self.clicks += 1
        point = model.object_positions(poses)[hit.body] if hit.is_object else hit.point
        self.reach(np.array([point[0], point[1], start[2]]))
        what = f"the **{object_label(hit.body)}**" if hit.is_object else f"the {object_label(hit.body)}"
        frame = self.client.latest_pose() if self.client is not None else None
        held = None
        if frame is not None and self._rules is not None:
            ee = np.asarray(frame.ee_pos, dtype=np.float64)
            held = self._rules.held(ee, float(frame.gripper), model.object_positions(poses))
        then = (
            f"**Down** to lower the {object_label(held)}, **Open** to release it."
            if held
            else "**Down** to descend, **Close** to grasp."
        )
        self.status.content = f"Moving over {what} at ({point[0]:.3f}, {point[1]:.3f}). {then}"

    def move_height(self, which: str) -> None:
        """Down: to the grasp height of the object below, the place height of one held, or just above the table;
        Up: to the carrying height."""
        model, rules, poses, start = self._scene_model, self._rules, self._poses, self._motion_base()
        if model is None or rules is None or poses is None or start is None or self.client is None:
            return
        frame = self.client.latest_pose()
        ee = np.asarray(frame.ee_pos, dtype=np.float64) if frame is not None else start
        if which == "Up":
            z, why = rules.up(ee), "up to carrying height"
        else:
            z, why = down_height(model, rules, poses, ee, self._gripper)
        self.reach(np.array([start[0], start[1], z]))
        self.status.content = f"{which}: {why} (grasp point to {100 * z:.1f} cm)."

    def nudge(self, axis) -> None:
        start = self._motion_base()
        if start is None:
            return
        step = NUDGE_STEPS.get(self.nudge_step.value, 0.01)
        self.reach(start + step * np.asarray(axis, dtype=np.float64))

    def _on_hotkey(self, what: str, axis) -> None:
        if self.tab.mode != "teleop":
            return
        if what == "nudge":
            self.nudge(axis)
        elif what in ("down", "up"):
            self.move_height(what.capitalize())
        else:
            self.set_gripper(1.0 if what == "close" else 0.0)

    def _cues_loop(self) -> None:
        """Redraw the depth cues and the distance line while the live session is shown."""
        shown = ""
        while not self._closed:
            time.sleep(1.0 / CUES_HZ)
            model, rules, poses, client = self._scene_model, self._rules, self._poses, self.client
            if self.tab.mode != "teleop" or model is None or rules is None or poses is None or client is None:
                continue
            frame = client.latest_pose()
            if frame is None:
                continue
            ee = np.asarray(frame.ee_pos, dtype=np.float64)
            objects = model.object_positions(poses)
            held = rules.held(ee, float(frame.gripper), objects)
            below = model.cast(poses, ee, (0.0, 0.0, -1.0), skip=frozenset({held} if held else ()))
            focus = held or rules.under(ee, objects)
            try:
                self.cues.show(ee, below, model.outline(poses, focus) if focus else None)
            except Exception:  # a tab closing under the loop: the next pass sees it closed
                continue
            nearest = min(
                ((n, float(np.linalg.norm(p - ee))) for n, p in objects.items()),
                key=lambda x: x[1],
                default=None,
            )
            line = describe(ee, below, nearest, held)
            if line != shown:
                shown = line
                self.cue_line.content = line

    def _on_pose(self, frame: msg.PoseFrame) -> None:
        """Every pose frame of the session (Zenoh thread): to the scene, and latency bookkeeping."""
        self._poses = frame.poses_array()
        ack = None
        if frame.ack_seq >= 0:
            now = time.perf_counter()
            with self._pending_lock:
                done = [s for s in self._pending if s <= frame.ack_seq]
                sent = [self._pending.pop(s) for s in done]
            for t in sent:
                self.app.stats.add("ack", 1e3 * (now - t))
            if sent:
                ack = (frame.ack_seq, min(sent))
        if self.tab.mode == "teleop":
            self.tab.push_poses(self._token, self._poses, ack)

    def _preview_loop(self) -> None:
        version = 0
        next_frustum = 0.0
        while not self._closed:
            client = self.client
            if client is None:
                time.sleep(0.2)
                continue
            frame, version = client.frames.wait_newer(version, 0.5)
            if frame is None or self._closed:
                continue
            try:
                image = frame.to_array()
            except msg.ProtocolError:
                continue
            small = image[
                :: max(1, image.shape[0] // PREVIEW_SIZE[0]), :: max(1, image.shape[1] // PREVIEW_SIZE[1])
            ]
            self.preview.image = small
            if self.tab.mode == "teleop" and time.monotonic() >= next_frustum:
                self.tab.view.set_camera_image(image)
                next_frustum = time.monotonic() + 1.0 / FRUSTUM_IMAGE_HZ
            time.sleep(1.0 / PREVIEW_HZ / 2)

    # ------------------------------------------------------------------ recording
    def _set_recording_ui(self, recording: bool) -> None:
        self.record.disabled = recording
        self.stop.disabled = not recording
        self.discard.disabled = not recording
        self.rec_status.content = "### ● REC — recording" if recording else ""

    def start_recording(self) -> None:
        if self.client is None:
            raise RuntimeError("no teleop session yet")
        self.show_live()
        if self._recording:
            self._drop_draft()
        info = self.info
        assert info is not None  # a client has an open session
        role = DEFAULT_ROLE.get(info.robot, "expert")
        draft = new_draft_id()
        self.app.drafts.create(
            draft,
            {
                "scene": info.scene,
                "robot": info.robot,
                "task": info.task,
                "seed": info.seed,
                "control_dt": info.control_dt,
                "role": role,
            },
        )
        try:
            self.client.start_recording(role=role, reset=True, draft=draft)
            self._rest_pending, self._target, self._goal = True, None, None
            self._gripper = 0.0  # a reset scene's gripper is open
        except BaseException:
            self.app.drafts.discard(draft)
            raise
        self._draft, self._fork_note, self._fork_origin = draft, "", {}
        self._recording = True
        self._success_touched = self._success_written = False
        self.success.value = False
        frame = self.client.latest_pose()
        self._place_gizmo(np.asarray(frame.ee_pos) if frame is not None else None)
        self._remember_rest()
        self._set_recording_ui(True)
        self.status.content = "Recording — move the arm, then **Stop & save** or **Discard**."

    def stop_and_save(self) -> None:
        if self.client is None or not self._recording:
            return
        self.stop.disabled = self.discard.disabled = True  # saving takes a while: no second stop meanwhile
        verdict = bool(self.success.value)
        self.status.content = "Stopping — rendering and storing the episode…"
        try:
            outcome = self.client.stop_recording(wait=True, success=verdict)
        except bus.RemoteError as e:
            self.status.content = f"Still recording: {e.message}"
            self.tab.notify("Not saved yet", e.message, error=True)
            self._set_recording_ui(True)
            return
        except bus.BusError as e:  # no answer: the recording goes on unless the worker is gone (Workers tab)
            self.status.content = f"Still recording: the sim worker did not answer ({e}); try again."
            self.tab.notify("Not saved yet", str(e), error=True)
            self._set_recording_ui(True)
            return
        except TimeoutError as e:  # the worker took the recording but has not reported it stored
            self._recording = False
            self._set_recording_ui(False)
            self.status.content = f"**Not confirmed**: {e}; the worker may still store it (see Datasets)."
            self.tab.notify("Episode not confirmed", str(e), error=True)
            return
        self._recording = False
        self._set_recording_ui(False)
        if isinstance(outcome, msg.EpisodeSaved):
            if outcome.draft is not None:
                self.app.drafts.discard(outcome.draft)  # the episode holds it now
            what = f" (continues {self._fork_note})" if self._fork_note else ""
            self._draft, self._fork_note, self._fork_origin = None, "", {}
            self.status.content = (
                f"Saved `{outcome.episode}` — {outcome.steps} steps, {outcome.frames} frames, "
                f"success={outcome.success}, {outcome.role}{what}."
            )
            self.tab.notify("Episode saved", f"{outcome.task}: {outcome.episode}")
            self.app.dataset_changed()
        else:
            self.status.content = f"**Not stored**: {outcome.reason} (kept at `{outcome.kept_at}`)."
            self.tab.notify("Episode not stored", f"{outcome.reason}; kept at {outcome.kept_at}", error=True)

    def discard_recording(self) -> None:
        if self.client is None or not self._recording:
            return
        self.client.discard_recording()
        self._drop_draft()
        self._recording = False
        self._set_recording_ui(False)
        self.status.content = "Recording discarded."

    def _on_success(self, event) -> None:
        if event.client is not None:
            self._success_touched = True

    # ------------------------------------------------------------------ deleting
    def _confirm_delete(self, selected: bool) -> None:
        store = self.app.store
        if selected:
            eid = self.episode_list.value.split(" ")[0]
            try:
                meta = store.get(eid)
            except KeyError:
                self.tab.notify("Nothing to delete", "Choose an episode first.", error=True)
                return
        else:
            mine = store.episodes(source="teleop", newest_first=True, limit=1, task=self.task.value)
            if not mine:
                self.tab.notify("Nothing to delete", f"No teleop episode of {self.task.value}.", error=True)
                return
            meta = mine[0]
        client = self.tab.client
        with client.gui.add_modal("Delete this episode?") as modal:
            client.gui.add_markdown(
                f"`{meta.id}` — {meta.task}, {meta.role} by {meta.embodiment} ({meta.source}), "
                f"{meta.num_frames} frames. This cannot be undone."
            )
            yes = client.gui.add_button("Delete", color="red")
            no = client.gui.add_button("Keep it")

        def delete(_) -> None:
            modal.close()
            try:
                store.delete_episode(meta.id)
            except KeyError:
                self.tab.notify("Already gone", f"{meta.id} was deleted meanwhile.")
                return
            self.app.dataset_changed()
            self.status.content = f"Deleted `{meta.id}`."
            self.tab.notify("Episode deleted", meta.id)

        yes.on_click(delete)
        no.on_click(lambda _: modal.close())

    # ------------------------------------------------------------------ scene / task choices
    def _on_scene(self, event) -> None:
        if event.client is None:
            return
        self.narrow_choices()
        self.tab.run(self.open, "opening the session")

    def narrow_choices(self) -> None:
        """Task and robot choices for the chosen scene (Meta-World has the Sawyer only)."""
        scene = self.scene.value
        tasks = scene_tasks(scene)
        self.task.options = tuple(tasks)
        self.task.value = tasks[0]
        self.task_note.content = held_out_note(tasks[0])
        self.robot.options = ("sawyer",) if scene == "metaworld" else TABLETOP_ROBOTS
        if self.robot.value not in self.robot.options:
            self.robot.value = "sawyer"

    def _on_task(self, event) -> None:
        self.task_note.content = held_out_note(self.task.value)
        if event.client is not None:
            self.tab.run(self.reset, "resetting the scene")

    def _on_scene_button(self, event) -> None:
        if event.target.value == "New seed":
            self.seed.value = int(np.random.default_rng().integers(0, 100_000))
        else:
            self.tab.run(self.reset, "resetting the scene")

    # ------------------------------------------------------------------ refresh
    def refresh(self) -> None:
        client = self.client
        if client is not None and not self.app.hub.directory.is_alive(client.worker) and not self._lost:
            # The worker hosting this session is gone (killed, machine lost): wait for another one.
            self._lost = True
            log.warning(
                "tab %s: sim worker %s left the bus; reopening the teleop session on the next one",
                self.tab.client.client_id,
                client.worker,
            )
            self.tab.notify(
                "Sim worker lost",
                f"{client.worker} left the bus; reopening on the next sim worker.",
                error=True,
            )
            self.tab.run(self._drop_client, "dropping the lost session")
        if client is not None and self._recording:
            state, _ = client.state.get()
            if isinstance(state, msg.SessionState) and state.state == "recording":
                seconds = state.recorded_steps * (self.info.control_dt if self.info else 0.0)
                self.rec_status.content = f"### ● REC {seconds:5.1f} s — {state.recorded_steps} steps"
                if not self._success_touched:
                    if self.success.value != self._success_written:
                        # the person's tick arrived before its callback ran: it is theirs, do not write over it
                        self._success_touched = True
                    elif self.success.value != state.success:
                        self.success.value = self._success_written = bool(state.success)
        self._refresh_drafts()
        if self.app.dataset_version != self._list_version or self.task.value != self._list_task:
            self._list_version, self._list_task = self.app.dataset_version, self.task.value
            metas = self.app.store.episodes(task=self.task.value, newest_first=True, limit=100)
            options = tuple(
                f"{m.id} · {m.role}/{m.embodiment} · {m.source} · {'✔' if m.success else '✘' if m.success is False else '?'}"
                for m in metas
            ) or ("(none)",)
            if self.episode_list.options != options:
                self.episode_list.options = options

    def _refresh_drafts(self) -> None:
        """List drafts no session of this studio is writing (a recording interrupted by a stop of the studio)."""
        live = {t.teleop._draft for t in list(self.app.tabs.values())} | {self._draft, self._resume}
        shown = tuple(
            f"{d.id} · {d.header.get('task')} · {d.steps} ticks"
            + (" · fork" if d.header.get("prefix") else "")
            for d in self.app.drafts.drafts()
            if d.id not in live
        )
        if shown != self._drafts_shown:
            self._drafts_shown = shown
            self.draft_list.options = shown or ("(none)",)
            self.drafts_folder.visible = bool(shown)

    def _drop_client(self) -> None:
        client, self.client, self.info = self.client, None, None
        if self._recording and self._draft is not None:
            # Nothing recorded is lost: the next session continues the draft, still recording.
            self._resume, self._draft = self._draft, None
            self.status.content = (
                f"The sim worker was lost mid-recording; {self.keeper.kept.get(self._resume, 0)} ticks are "
                "kept in the draft. Resuming on the next sim worker…"
            )
        self._recording = False
        self._set_recording_ui(False)
        if client is not None:
            client.close()
        self._lost = False
        self._await_worker()

    def close(self) -> None:
        self._closed = True
        if self.client is not None:
            self.client.close()
