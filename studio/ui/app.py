"""The studio's browser app: every tab gets its own teleop session, mirrored scene and panels.

Today the app hosts teleoperation and recording (drag the gizmo, open/close the gripper, record, save
into the episode store) with the simulation running in this process; the panels for training,
imitation and the rollout inspector attach to the Zenoh workers as those land.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import viser

from studio.data.store import EpisodeStore
from studio.sim.tasks import list_tasks
from studio.ui.scene_mirror import SceneMirror
from studio.ui.teleop import TeleopSession

HINTS = """**Teleop & record.** Drag the gizmo at the gripper to move the arm (it follows through IK);
use *Close* / *Open* for the gripper. *Record* starts an episode, *Stop & save* stores it in the
dataset (success is pre-filled by the task's check), *Discard* drops it. Sawyer recordings are expert
demonstrations, Panda recordings agent trajectories."""

POSE_HZ = 30.0


class ClientPanel:
    """What one browser tab sees and drives."""

    def __init__(self, app: StudioApp, client: viser.ClientHandle):
        self.app, self.client = app, client
        self.session: TeleopSession | None = None
        self.mirror: SceneMirror | None = None
        self.gizmo = None
        self._last_push = 0.0
        gui = client.gui
        with gui.add_folder("Teleop & record"):
            gui.add_markdown(HINTS)
            self.robot = gui.add_dropdown("Robot", ("sawyer", "panda"), initial_value="sawyer")
            self.task = gui.add_dropdown("Task", tuple(list_tasks()), initial_value=list_tasks()[0])
            self.seed = gui.add_number("Seed", initial_value=0, min=0, step=1)
            new_seed = gui.add_button("New seed")
            reset = gui.add_button("Reset")
            grip = gui.add_button_group("Gripper", ("Open", "Close"))
            self.record = gui.add_button("Record", color="red")
            self.stop = gui.add_button("Stop & save", disabled=True)
            self.discard = gui.add_button("Discard", disabled=True)
            self.success = gui.add_checkbox("Mark as success", initial_value=False)
            self.status = gui.add_markdown("Starting the simulator…")
            self.preview = gui.add_image(np.zeros((120, 160, 3), dtype=np.uint8), label="External camera")
            delete_last = gui.add_button("Delete last episode")
        self.robot.on_update(lambda _: self.open_session())
        self.task.on_update(lambda _: self.open_session())
        reset.on_click(lambda _: self.open_session())
        new_seed.on_click(lambda _: self._new_seed())
        grip.on_click(lambda e: self.session and self.session.set_gripper(1.0 if e.target.value == "Close" else 0.0))
        self.record.on_click(lambda _: self._start())
        self.stop.on_click(lambda _: self._stop_and_save())
        self.discard.on_click(lambda _: self._discard())
        delete_last.on_click(lambda _: self._delete_last())
        self.open_session()

    # ------------------------------------------------------------------ session
    def open_session(self) -> None:
        task = self.task.value
        scene = task.split("/")[0]
        if self.session is not None:
            self.session.close()
        if self.mirror is not None:
            self.mirror.remove()
        self.session = TeleopSession(scene, self.robot.value, task, int(self.seed.value), on_tick=self._on_tick)
        self.mirror = SceneMirror(self.client.scene, self.session.env.model)
        ee = self.session.env.ee_pos
        if self.gizmo is None:
            self.gizmo = self.client.scene.add_transform_controls(
                "/gizmo", scale=0.15, disable_rotations=True, position=ee)
            self.gizmo.on_update(lambda _: self.session and self.session.set_target(self.gizmo.position))
        self.gizmo.position = ee
        self._set_recording_ui(False)
        self.status.content = f"**{task}** with the **{self.robot.value}**, seed {int(self.seed.value)}. Ready."

    def _new_seed(self) -> None:
        self.seed.value = int(np.random.default_rng().integers(0, 1_000_000))
        self.open_session()

    def _on_tick(self, session: TeleopSession) -> None:
        now = time.perf_counter()
        if now - self._last_push < 1.0 / POSE_HZ or self.mirror is None:
            return
        self._last_push = now
        with session.lock:
            self.mirror.update(session.env.data)
        if session.env.steps % 10 == 0:
            self.preview.image = session.env.render(size=(120, 160))

    # ------------------------------------------------------------------ recording
    def _set_recording_ui(self, recording: bool) -> None:
        self.record.disabled = recording
        self.stop.disabled = not recording
        self.discard.disabled = not recording

    def _start(self) -> None:
        self.session.start_recording()
        self._set_recording_ui(True)
        self.status.content = "● **Recording** — move the arm, then *Stop & save* or *Discard*."

    def _discard(self) -> None:
        self.session.discard_recording()
        self._set_recording_ui(False)
        self.status.content = "Recording discarded."

    def _stop_and_save(self) -> None:
        self._set_recording_ui(False)
        rec = self.session.stop_recording()
        if rec is None:
            self.status.content = "Nothing was recorded."
            return
        rec.success = bool(rec.success or self.success.value)
        role = "expert" if rec.robot == "sawyer" else "agent"
        meta = self.app.store.add_episode(rec, role=role, source="teleop")
        self.status.content = f"Saved episode `{meta.id}` ({rec.num_steps} steps, success={rec.success})."
        self.client.add_notification("Episode saved", f"{rec.task}: {meta.id}", auto_close_seconds=4.0)

    def _delete_last(self) -> None:
        meta = self.app.store.delete_last(source="teleop")
        self.status.content = f"Deleted episode `{meta.id}`." if meta else "No teleop episode to delete."

    def close(self) -> None:
        if self.session is not None:
            self.session.close()


class StudioApp:
    """The viser server and one :class:`ClientPanel` per connected tab."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, data_dir=None):
        self.store = EpisodeStore(data_dir)
        self.server = viser.ViserServer(host=host, port=port, label="OSVI Studio")
        self.server.scene.set_up_direction("+z")
        self.panels: dict[int, ClientPanel] = {}
        self._lock = threading.Lock()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def _connect(self, client: viser.ClientHandle) -> None:
        client.camera.position = (0.0, 1.6, 0.9)
        client.camera.look_at = (0.0, 0.35, 0.1)
        panel = ClientPanel(self, client)
        with self._lock:
            self.panels[client.client_id] = panel

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            panel = self.panels.pop(client.client_id, None)
        if panel is not None:
            panel.close()

    def stop(self) -> None:
        for panel in list(self.panels.values()):
            panel.close()
        self.server.stop()
        self.store.close()
