"""One client's teleop session on a sim worker: a simulator stepping in real time, driven over the bus.

The session owns the live control: opening and resetting the scene, end-effector targets and the gripper,
the published poses and camera frames, and the owner token its commands must carry. What it records goes to
its :class:`~studio.backend.recording_sink.RecordingSink`, which stores finished recordings and sends draft
chunks on threads of its own. The session's two threads, so that nothing slow ever delays physics:

* **sim** — one :meth:`studio.sim.env.SimEnv.step` per control tick (``control_dt``, 100 Hz by default),
  with the newest :class:`~studio.backend.messages.EeTarget` (latest wins: commands that arrive between
  two ticks replace each other). A new command runs the next tick at once if that keeps simulated time
  at most one tick ahead of wall time, so command-to-pose latency is the IK + physics time, not the
  tick phase, while the simulation still runs in real time.
  Each tick publishes a :class:`~studio.backend.messages.PoseFrame` with Zenoh's drop-on-congestion
  policy: a slow subscriber loses stale poses, it never slows the loop. Requests that change the
  simulation (reset, recording) run on this thread between ticks.
* **render** — camera images for :class:`~studio.backend.messages.RequestFrame` /
  :class:`~studio.backend.messages.StreamFrames` and the frames of finished recordings, rendered on a
  second ``SimEnv`` (same scene, same task layout) set to a snapshot of the physics state.

A session opened with a :class:`~studio.backend.messages.ForkStart` continues a recorded episode (a rollout
forked at a tick, or a draft whose worker died): its last physics state is restored exactly and the
session is recording from there, the episode's earlier ticks included, at the episode's control period.
"""

from __future__ import annotations

import collections
import hmac
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import mujoco
import numpy as np
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import EpisodeDestination
from studio.backend.recording_sink import DEFAULT_ROLE, MIN_RECORDED_STEPS, RecordingSink, StoppedRecording
from studio.backend.scene_state import body_names, pose_frame, scene_geometry
from studio.sim.env import SimEnv, Simulator, make_env

_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


#: The codes of :class:`~studio.backend.messages.ErrorReply`.
ErrorCode = Literal["bad_request", "not_found", "busy", "unavailable", "conflict", "internal"]


class SessionError(RuntimeError):
    """A request the session cannot serve; ``code`` is an ErrorReply code."""

    def __init__(self, code: ErrorCode, message: str):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class TeleopConfig:
    """Timing of a teleop session.

    Attributes:
        control_dt: seconds per control tick; the simulator rounds it to whole physics steps
            (10 ms = 5 × 2 ms, 100 Hz: a pose per tick keeps the stream well above 60 Hz even when the
            machine is loaded; at 62.5 Hz nominal, measured streams dipped to 59.5 Hz under load).
        command_lead: how far (in ticks) a new command may run its tick ahead of real time, so that it
            is applied at once instead of at the next tick.
        state_hz: how often the session's :class:`~studio.backend.messages.SessionState` is re-published.
    """

    control_dt: float = 0.01
    command_lead: float = 1.0
    state_hz: float = 2.0


@dataclass
class _Call:
    fn: Callable[[], Any]
    done: threading.Event
    result: Any = None
    error: BaseException | None = None

    def run(self) -> None:
        try:
            self.result = self.fn()
        except BaseException as e:  # handed back to the caller's thread
            self.error = e
        finally:
            self.done.set()


@dataclass(frozen=True)
class _Snapshot:
    state: np.ndarray
    step: int
    task: str
    seed: int


class TeleopSession:
    """A teleop session; created by the sim worker when a client sends :class:`OpenSession`.

    Raises :class:`SessionError` if the scene, robot or task is unknown.
    """

    def __init__(
        self,
        zsession: zenoh.Session,
        worker: str,
        session_id: str,
        request: msg.OpenSession,
        destination: EpisodeDestination,
        spool_dir: Path,
        config: TeleopConfig = TeleopConfig(),
        owner: str | None = None,
        drafts_dir: Path | None = None,
    ):
        self.zsession = zsession
        #: The owner token the session's commands must carry (None: commands need none; tests only).
        self.owner = owner
        self.worker = worker
        self.id = session_id
        self.request = request
        self.config = config
        size = (request.image_height, request.image_width)
        fork = request.fork
        self._control_dt = fork.control_dt if fork is not None else config.control_dt
        try:
            self.env = self._make_env(request.scene, request.robot, size)
        except ValueError as e:
            raise SessionError("bad_request", str(e)) from None
        except Exception as e:  # a scene file that no longer loads: say which and why
            raise SessionError(
                "bad_request",
                f"scene {request.scene!r} with the {request.robot} does not load: {type(e).__name__}: {e}",
            ) from None
        try:
            if fork is None:
                self.env.reset(request.task, request.seed)
            else:
                self._check_fork(fork)
                self.env.restore(request.task, request.seed, fork.states.to_array(), fork.gripper)
        except ValueError as e:
            self.env.close()
            raise SessionError("bad_request", str(e)) from None
        m = self.env.model
        max_w, max_h = int(m.vis.global_.offwidth), int(m.vis.global_.offheight)
        if request.image_width > max_w or request.image_height > max_h:
            self.env.close()
            raise SessionError(
                "bad_request",
                f"image size {request.image_height}x{request.image_width} exceeds the scene's render buffer "
                f"{max_h}x{max_w}",
            )
        self._describe_model()

        self._cond = threading.Condition()
        self._closed = False
        self._cmd: msg.EeTarget | None = None
        self._cmd_new = False
        self._last_seq = 0  # seq of the newest command taken
        self._calls: list[_Call] = []
        self._seq = 0
        self._snapshot = self._take_snapshot()

        self._render_cond = threading.Condition()
        self._render_jobs: collections.deque[tuple[str, Any]] = collections.deque()
        self._stream: msg.StreamFrames | None = None

        self._pose_pub = zsession.declare_publisher(
            keys.session_key(worker, session_id, "poses"),
            express=True,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self._frame_pub = zsession.declare_publisher(
            keys.session_key(worker, session_id, "frames"), congestion_control=zenoh.CongestionControl.DROP
        )
        #: What the session records, and where its finished recordings go.
        self.sink = RecordingSink(
            zsession,
            worker,
            session_id,
            destination,
            spool_dir,
            drafts_dir,
            self._publish_status,
            self.state,
            DEFAULT_ROLE.get(request.robot, "expert"),
            fork,
        )
        if fork is not None:
            self.sink.continue_fork(self.env, fork)
        status_key = keys.session_key(worker, session_id, "status")
        self._state_pub = zsession.declare_publisher(
            status_key
        )  # periodic: a newer state supersedes a lost one
        self._event_pub = zsession.declare_publisher(status_key, congestion_control=bus.MUST_ARRIVE)
        self._cmd_sub = bus.declare_subscriber(
            zsession, keys.session_key(worker, session_id, "cmd"), self._on_cmd, msg.EeTarget
        )
        self._threads = [
            threading.Thread(target=self._sim_loop, name=f"sim-{session_id}", daemon=True),
            threading.Thread(target=self._render_loop, name=f"render-{session_id}", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self.sink.start_threads()

    # ------------------------------------------------------------------ descriptions
    def _make_env(self, scene: str, robot: str, size: tuple[int, int]) -> Simulator:
        """The scene's simulator: a SimEnv at the session's control rate, or a Meta-World environment
        (``scene="metaworld"``, whose control rate is Meta-World's own)."""
        if scene == "metaworld":
            env: Simulator = make_env(scene, robot, image_size=size)
            return env
        return SimEnv(scene, robot, image_size=size, control_dt=self._control_dt)

    def _check_fork(self, fork: msg.ForkStart) -> None:
        """Refuse a fork this session cannot continue as recorded, with the reason."""
        if abs(self.env.control_dt - fork.control_dt) > 1e-9:
            raise ValueError(
                f"the episode was recorded at a control period of {fork.control_dt:g} s, this scene steps at "
                f"{self.env.control_dt:g} s: it cannot be continued at its own rate"
            )
        from studio.sim.recording import ARRAY_FIELDS

        missing = sorted(set(ARRAY_FIELDS) - set(fork.arrays))
        if missing:
            raise ValueError(f"the forked episode lacks the recorded arrays {missing}")

    def _describe_model(self) -> None:
        """Cameras and bodies of the current model (a Meta-World reset to another task changes the model)."""
        m = self.env.model
        # "external" (the observation camera) and "wrist" in every scene; Meta-World re-mounts two of its own.
        self.cameras = self.env.camera_names
        self.body_names = body_names(m)
        self._geometry: msg.SceneGeometry | None = None

    def _scene_geometry(self) -> msg.SceneGeometry:
        if self._geometry is None:
            self._geometry = scene_geometry(self.env.model)
        return self._geometry

    def _episode(self) -> tuple[str, int]:
        """The current episode's task name and seed (the env is reset when the session opens)."""
        task, seed = self.env.task, self.env.seed
        assert task is not None and seed is not None, "a session's env is reset in __init__"
        return task.name, seed

    def info(self) -> msg.SessionInfo:
        env = self.env
        task, seed = self._episode()
        return msg.SessionInfo(
            session=self.id,
            worker=self.worker,
            scene=env.scene,
            robot=env.robot,
            task=task,
            seed=int(seed),
            control_dt=float(env.control_dt),
            body_names=self.body_names,
            cameras=self.cameras,
            camera=env.camera_model("external").to_dict(),
            image_height=env.image_size[0],
            image_width=env.image_size[1],
            owner=self.owner,
        )

    def state(self, message: str = "") -> msg.SessionState:
        env = self.env
        recorded = self.sink.recorded_steps
        task, seed = self._episode()
        return msg.SessionState(
            session=self.id,
            state="closed" if self._closed else ("recording" if recorded is not None else "idle"),
            task=task,
            seed=int(seed),
            step=env.steps,
            recorded_steps=0 if recorded is None else recorded,
            saving=self.sink.saving,
            success=bool(env.success()),
            message=message[:4000],
        )

    def _publish_status(self, message: msg.Message) -> None:
        """A session state (latest wins), or an event the client waits for (an episode stored or not)."""
        publisher = self._state_pub if isinstance(message, msg.SessionState) else self._event_pub
        try:
            publisher.put(msg.encode(message))
        except zenoh.ZError:
            pass

    # ------------------------------------------------------------------ requests (any thread)
    def handle(self, request: msg.Message, query: zenoh.Query) -> Any:
        """Serve one control request; returns the reply or :data:`bus.DEFERRED`."""
        if isinstance(request, msg.ResetSession):
            return self.call(lambda: self._reset(request.task, request.seed))
        if isinstance(request, msg.StartRecording):
            return self.call(lambda: self._start_recording(request))
        if isinstance(request, msg.StopRecording):
            return self.call(lambda: self._stop_recording(request.success))
        if isinstance(request, msg.DiscardRecording):
            return self.call(self._discard_recording)
        if isinstance(request, msg.RequestFrame):
            self._check_camera(request.camera)
            with self._render_cond:
                self._render_jobs.append(("frame", (request, query)))
                self._render_cond.notify()
            return bus.DEFERRED
        if isinstance(request, msg.StreamFrames):
            self._check_camera(request.camera)
            with self._render_cond:
                self._stream = request if request.hz > 0 else None
                self._render_cond.notify()
            return msg.Ack(
                message=f"streaming {request.camera} at {request.hz:g} Hz" if request.hz > 0 else "stopped"
            )
        if isinstance(request, msg.GetGeometry):
            return self.call(self._scene_geometry)
        raise SessionError("bad_request", f"{type(request).__name__} is not a teleop session request")

    def _check_camera(self, camera: str) -> None:
        if camera not in self.cameras:
            raise SessionError(
                "bad_request", f"unknown camera {camera!r}; this scene has {list(self.cameras)}"
            )

    def call(self, fn: Callable[[], Any], timeout: float = 10.0) -> Any:
        """Run ``fn`` on the sim thread between two ticks and return its result (or raise its error)."""
        c = _Call(fn, threading.Event())
        with self._cond:
            if self._closed:
                raise SessionError("not_found", f"session {self.id} is closed")
            self._calls.append(c)
            self._cond.notify_all()
        if not c.done.wait(timeout):
            raise SessionError("internal", f"the simulation did not answer within {timeout} s")
        if c.error is not None:
            raise c.error
        return c.result

    def _on_cmd(self, cmd: msg.EeTarget, sample: zenoh.Sample | None) -> None:
        if self.owner is not None and (
            sample is None or not hmac.compare_digest(bus.attachment_bytes(sample), self.owner.encode())
        ):
            bus.bad_input_log.warning(
                f"cmd-owner:{self.id}", "session %s: dropped a command without its owner's token", self.id
            )
            return
        with self._cond:
            # Out-of-order stale commands are dropped, and so is one too far ahead (it would hold every later one).
            if self._last_seq <= cmd.seq <= self._last_seq + msg.MAX_SEQ_STEP:
                self._last_seq = cmd.seq
                self._cmd = cmd
                self._cmd_new = True
                self._cond.notify_all()
            else:
                bus.bad_input_log.warning(
                    f"cmd-seq:{self.id}",
                    "session %s: dropped a command with seq %d (last %d)",
                    self.id,
                    cmd.seq,
                    self._last_seq,
                )

    # ------------------------------------------------------------------ sim thread
    def _sim_loop(self) -> None:
        # Simulated time follows wall time: tick n is due at next_due. A pending command may run its tick
        # up to `lead` early (so it is applied at once), never more, so the simulation never runs ahead
        # of real time by more than that; after falling behind by more than a tick it skips ahead
        # instead of bursting.
        dt = self.env.control_dt
        lead = dt * self.config.command_lead
        next_due = time.monotonic() + dt
        next_state = 0.0
        while True:
            with self._cond:
                while True:
                    if self._closed:
                        return
                    now = time.monotonic()
                    if self._calls or now >= next_due or (self._cmd_new and now >= next_due - lead):
                        break
                    wake = next_due - lead if self._cmd_new else next_due
                    self._cond.wait(max(0.0, wake - now))
                calls, self._calls = self._calls, []
            for c in calls:
                c.run()
            now = time.monotonic()
            with self._cond:
                if not (now >= next_due or (self._cmd_new and now >= next_due - lead)):
                    continue
                cmd, self._cmd_new = self._cmd, False
            try:
                self._tick(cmd)
            except Exception:
                bus.log.error("session %s: control tick failed:\n%s", self.id, traceback.format_exc())
            next_due += dt
            if now - next_due > dt:
                next_due = now + dt
            if now >= next_state:
                next_state = now + 1.0 / self.config.state_hz
                self._publish_status(self.state())

    def _tick(self, cmd: msg.EeTarget | None) -> None:
        env = self.env
        if cmd is not None:
            env.step(np.asarray(cmd.pos, dtype=np.float64), cmd.gripper)
        else:
            env.step(env.target, env.gripper_cmd)
        self.sink.tick(env.control_dt)
        self._publish_pose(-1 if cmd is None else cmd.seq)

    def _publish_pose(self, ack_seq: int) -> None:
        env = self.env
        self._seq += 1
        frame = pose_frame(
            env.data,
            seq=self._seq,
            step=env.steps,
            ack_seq=ack_seq,
            ee_pos=env.ee_pos,
            gripper=env.gripper_cmd,
        )
        snapshot = self._take_snapshot()
        with self._render_cond:
            self._snapshot = snapshot
        try:
            self._pose_pub.put(msg.encode(frame))
        except zenoh.ZError:
            pass

    def _take_snapshot(self) -> _Snapshot:
        env = self.env
        state = np.empty(mujoco.mj_stateSize(env.model, _STATE))
        mujoco.mj_getState(env.model, env.data, state, _STATE)
        task, seed = self._episode()
        return _Snapshot(state, env.steps, task, int(seed))

    def _reset(self, task: str | None, seed: int | None) -> msg.SessionInfo:
        note = ""
        if self.sink.discard():
            note = "the unsaved recording was discarded by the reset"
        current_task, current_seed = self._episode()
        try:
            self.env.reset(task or current_task, current_seed if seed is None else seed)
        except ValueError as e:
            raise SessionError("bad_request", str(e)) from None
        self._describe_model()
        with self._cond:
            self._cmd, self._cmd_new = None, False
        self._publish_pose(-1)
        self._publish_status(self.state(note))
        return self.info()

    def _start_recording(self, request: msg.StartRecording) -> msg.SessionState:
        if self.sink.recording:
            raise SessionError("conflict", "already recording; stop or discard first")
        if request.reset:
            self.env.reset(*self._episode())
            with self._cond:
                self._cmd, self._cmd_new = None, False
            self._publish_pose(-1)
        self.sink.start(self.env, request.role, request.draft)
        state = self.state("recording")
        self._publish_status(state)
        return state

    def _stop_recording(self, success: bool | None = None) -> msg.SessionState:
        recorded = self.sink.recorded_steps
        if recorded is None:
            raise SessionError("conflict", "not recording")
        if recorded < MIN_RECORDED_STEPS:
            raise SessionError(
                "conflict",
                f"recording too short: {recorded} steps, need at least {MIN_RECORDED_STEPS}; keep going",
            )
        task, seed = self._episode()
        job = self.sink.stop(self.env, task, int(seed), success)
        with self._render_cond:
            self._render_jobs.append(("finish", job))
            self._render_cond.notify()
        state = self.state(f"saving {len(job.rows)} steps")
        self._publish_status(state)
        return state

    def _discard_recording(self) -> msg.SessionState:
        if not self.sink.discard():
            raise SessionError("conflict", "not recording")
        state = self.state("recording discarded")
        self._publish_status(state)
        return state

    # ------------------------------------------------------------------ render thread
    def _render_loop(self) -> None:
        render_env: Simulator | None = None
        layout: tuple[str, int] | None = None
        next_stream = 0.0
        try:
            while True:
                with self._render_cond:
                    while True:
                        if self._closed and not any(kind == "finish" for kind, _ in self._render_jobs):
                            return
                        stream = self._stream
                        now = time.monotonic()
                        if self._render_jobs or (
                            stream is not None and now >= next_stream and not self._closed
                        ):
                            break
                        timeout = None if stream is None else max(0.0, next_stream - now)
                        self._render_cond.wait(timeout if timeout is not None else 1.0)
                    job = self._render_jobs.popleft() if self._render_jobs else None
                    snapshot = self._snapshot
                if render_env is None:
                    render_env = self._make_env(self.env.scene, self.env.robot, self.env.image_size)
                if job is None:
                    assert stream is not None  # without a job, the loop only wakes for a stream frame
                    next_stream = time.monotonic() + 1.0 / stream.hz
                    layout = self._render_snapshot(render_env, layout, snapshot)
                    frame = msg.ImageFrame.from_array(
                        render_env.render(stream.camera),
                        camera=stream.camera,
                        step=snapshot.step,
                        encoding=stream.encoding,
                        quality=stream.quality,
                    )
                    self._frame_pub.put(msg.encode(frame))
                elif job[0] == "frame":
                    request, query = job[1]
                    try:
                        layout = self._render_snapshot(render_env, layout, snapshot)
                        frame = msg.ImageFrame.from_array(
                            render_env.render(request.camera),
                            camera=request.camera,
                            step=snapshot.step,
                            encoding=request.encoding,
                            quality=request.quality,
                        )
                        bus.reply(query, frame)
                        self._frame_pub.put(msg.encode(frame))
                    except Exception as e:
                        bus.log.exception("session %s: rendering failed", self.id)
                        bus.reply(query, msg.ErrorReply(code="internal", message=f"rendering failed: {e}"))
                    finally:
                        query.drop()
                else:
                    stopped: StoppedRecording = job[1]
                    try:
                        if layout != (stopped.task, stopped.seed):
                            render_env.reset(stopped.task, stopped.seed)
                            layout = (stopped.task, stopped.seed)
                        self.sink.store(stopped.render(render_env), stopped)
                    except Exception as e:
                        bus.log.exception("session %s: finishing a recording failed", self.id)
                        self.sink.not_rendered(e)
        finally:
            with self._render_cond:
                pending = list(self._render_jobs)
                self._render_jobs.clear()
            for kind, item in pending:
                if kind == "frame":
                    bus.reply(item[1], msg.ErrorReply(code="not_found", message="session closed"))
                    item[1].drop()
            if render_env is not None:
                render_env.close()

    def _render_snapshot(
        self, env: Simulator, layout: tuple[str, int] | None, snap: _Snapshot
    ) -> tuple[str, int]:
        if layout != (snap.task, snap.seed):
            env.reset(snap.task, snap.seed)  # moves the target zones to where the sim has them
        mujoco.mj_setState(env.model, env.data, snap.state, _STATE)
        mujoco.mj_forward(env.model, env.data)
        return (snap.task, snap.seed)

    # ------------------------------------------------------------------ closing
    def close(self, wait_s: float = 60.0) -> None:
        """Stop the session; recordings being finished or stored are completed first (up to ``wait_s``)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        with self._render_cond:
            self._render_cond.notify_all()
        self.sink.close()
        deadline = time.monotonic() + wait_s
        for t in self._threads + self.sink.threads:
            t.join(max(0.1, deadline - time.monotonic()))
        self._publish_status(self.state("closed"))
        for entity in (self._cmd_sub, self._pose_pub, self._frame_pub, self._state_pub, self._event_pub):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self.sink.undeclare()
        self.env.close()
