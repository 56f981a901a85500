"""The client side of a teleop session: what the UI (and the bus benchmark) use to drive a sim worker.

    client = TeleopClient(session, worker)
    info = client.open("pick_place", "panda", "pick_place/cube->red", seed=0)
    seq = client.set_target(pos, gripper=0.0)       # latest wins; poses stream back
    pose = client.wait_ack(seq)                     # the first PoseFrame that applied it
    client.start_recording(); ...; saved = client.stop_recording()

Commands stream as *latest wins*: the bus drops a command when the link's queue is full (a loaded machine
fills it with a burst), so the client sends its newest command again, same ``seq``, until a pose frame says the
worker applied it (:data:`RESEND_AFTER_S`); a motion's last target and a gripper change are never lost.

The client holds a liveliness token for its session, so the worker closes the session if the client
process dies. The worker's answer to ``open`` carries the session's owner token, which the client then attaches
to every request and command (:mod:`studio.backend.sim_worker`); nobody else can drive or stop the session.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Literal, overload

import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.presence import Directory

#: The newest command, not yet applied by the worker this long after it was sent, is sent again (same seq).
RESEND_AFTER_S = 0.2


def choose_sim_worker(directory: Directory) -> str:
    """The connected sim worker with the fewest teleop sessions; raises BusError if there is none."""
    candidates = [
        (e.status.sessions, e.joined_at, e.worker)
        for e in directory.workers("sim")
        if e.status is not None and e.status.state != "stopping"
    ]
    if not candidates:
        raise bus.BusError("no sim worker is connected (start one with `studio worker sim`)")
    return min(candidates, key=lambda c: (c[0], c[1]))[2]


class TeleopClient:
    """One teleop session on ``worker`` (a new random session id unless ``session_id`` is given)."""

    def __init__(
        self,
        zsession: zenoh.Session,
        worker: str,
        session_id: str | None = None,
        *,
        timeout: float = 10.0,
        on_pose: Callable[[msg.PoseFrame], None] | None = None,
        on_status: Callable[[msg.Message], None] | None = None,
        on_draft: Callable[[msg.DraftChunk], None] | None = None,
    ):
        self.zsession = zsession
        self.worker = keys.check_chunk(worker, "worker id")
        self.session_id = keys.check_chunk(session_id or f"s-{secrets.token_hex(4)}", "session id")
        self.timeout = timeout
        self.info: msg.SessionInfo | None = None
        self._seq = 0
        self._seq_lock = threading.Lock()
        #: The newest command while the worker has not applied it: (seq, encoded, monotonic time last sent).
        self._unapplied: tuple[int, bytes, float] | None = None
        self.resent = 0  # commands sent again because the worker had not applied them
        self._owner: bytes | None = None  # the session's owner token, from the worker's answer to open
        self.poses = bus.Latest()
        self.frames = bus.Latest()
        self.state = bus.Latest()
        self._events_cond = threading.Condition()
        self.episodes: list[msg.EpisodeSaved | msg.EpisodeNotSaved] = []
        self._on_pose, self._on_status, self._on_draft = on_pose, on_status, on_draft

        key = lambda leaf: keys.session_key(self.worker, self.session_id, leaf)  # noqa: E731
        self._ctl_key = key("ctl")
        self._token = zsession.liveliness().declare_token(key("client"))
        self._cmd_pub = zsession.declare_publisher(
            key("cmd"),
            express=True,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self._subs = [
            bus.declare_subscriber(zsession, key("poses"), self._pose, msg.PoseFrame),
            bus.declare_subscriber(zsession, key("frames"), lambda m, _s: self.frames.put(m), msg.ImageFrame),
            bus.declare_subscriber(
                zsession,
                key("status"),
                self._status,
                (msg.SessionState, msg.EpisodeSaved, msg.EpisodeNotSaved),
            ),
            bus.declare_subscriber(zsession, key("draft"), self._draft, msg.DraftChunk),
        ]

    # ------------------------------------------------------------------ streams
    def _pose(self, frame: msg.PoseFrame, _sample: Any) -> None:
        self.poses.put(frame)
        self._resend_unapplied(frame.ack_seq)
        if self._on_pose is not None:
            self._on_pose(frame)

    def _status(self, message: msg.Message, _sample: Any) -> None:
        if isinstance(message, msg.SessionState):
            self.state.put(message)
        else:
            # the subscription decodes only SessionState, EpisodeSaved and EpisodeNotSaved
            assert isinstance(message, (msg.EpisodeSaved, msg.EpisodeNotSaved))
            with self._events_cond:
                self.episodes.append(message)
                self._events_cond.notify_all()
        if self._on_status is not None:
            self._on_status(message)

    def _resend_unapplied(self, ack_seq: int) -> None:
        """Send the newest command again if the worker has not applied it within :data:`RESEND_AFTER_S`."""
        with self._seq_lock:
            if self._unapplied is None:
                return
            seq, payload, sent = self._unapplied
            if ack_seq >= seq:
                self._unapplied = None
                return
            now = time.monotonic()
            if now - sent < RESEND_AFTER_S:
                return
            self._unapplied = (seq, payload, now)
            self.resent += 1
        with contextlib.suppress(zenoh.ZError):
            self._cmd_pub.put(payload, attachment=self._owner)

    def _draft(self, chunk: msg.DraftChunk, _sample: Any) -> None:
        if self._on_draft is not None:
            self._on_draft(chunk)

    def _request(self, request: msg.Message, expect: Any, timeout: float | None = None) -> Any:
        return bus.request(
            self.zsession,
            self._ctl_key,
            request,
            expect,
            timeout=timeout or self.timeout,
            attachment=self._owner,
        )

    # ------------------------------------------------------------------ session
    def open(
        self,
        scene: str,
        robot: str,
        task: str,
        seed: int = 0,
        image_size: tuple[int, int] = (240, 320),
        fork: msg.ForkStart | None = None,
    ) -> msg.SessionInfo:
        """Open (or re-open) the session; building the simulator takes about a second.

        With ``fork`` the session continues that recorded episode of (task, seed) from its last tick and is
        recording (see :mod:`studio.backend.forking`).
        """
        request = msg.OpenSession(
            scene=scene,
            robot=robot,
            task=task,
            seed=seed,
            image_height=image_size[0],
            image_width=image_size[1],
            fork=fork,
        )
        info = self._request(request, msg.SessionInfo, timeout=max(self.timeout, 30.0))
        with self._seq_lock:
            self._owner = None if info.owner is None else info.owner.encode()
            self._seq = 0  # a new session counts its commands afresh
            self._unapplied = None
        self.info = info
        return info

    def reset(self, task: str | None = None, seed: int | None = None) -> msg.SessionInfo:
        self._forget_unapplied()  # a target meant for the scene before the reset
        self.info = self._request(msg.ResetSession(task=task, seed=seed), msg.SessionInfo)
        return self.info

    def set_target(self, pos: Iterable[float], gripper: float) -> int:
        """Send an end-effector target (world frame, metres) and gripper closure; returns its ``seq``."""
        x, y, z = (float(v) for v in pos)
        with self._seq_lock:
            self._seq += 1
            seq = self._seq
            payload = msg.encode(
                msg.EeTarget(seq=seq, pos=(x, y, z), gripper=min(1.0, max(0.0, float(gripper))))
            )
            self._unapplied = (seq, payload, time.monotonic())
        self._cmd_pub.put(payload, attachment=self._owner)
        return seq

    def _forget_unapplied(self) -> None:
        with self._seq_lock:
            self._unapplied = None

    def latest_pose(self) -> msg.PoseFrame | None:
        return self.poses.get()[0]

    def wait_ack(self, seq: int, timeout: float = 2.0) -> msg.PoseFrame | None:
        """The first pose frame that applied command ``seq`` (or a later one); None on timeout."""
        return self.poses.wait_until(lambda f: f.ack_seq >= seq, timeout)

    # ------------------------------------------------------------------ recording
    def start_recording(
        self, role: msg.Role | None = None, reset: bool = True, draft: str | None = None
    ) -> msg.SessionState:
        """Start recording; with ``draft`` the worker journals the ticks to this client as it goes."""
        if reset:
            self._forget_unapplied()
        return self._request(msg.StartRecording(role=role, reset=reset, draft=draft), msg.SessionState)

    def discard_recording(self) -> msg.SessionState:
        return self._request(msg.DiscardRecording(), msg.SessionState)

    @overload
    def stop_recording(
        self, wait: Literal[True] = True, timeout: float = 120.0, success: bool | None = None
    ) -> msg.EpisodeSaved | msg.EpisodeNotSaved: ...
    @overload
    def stop_recording(
        self, wait: Literal[False], timeout: float = 120.0, success: bool | None = None
    ) -> msg.SessionState: ...
    @overload
    def stop_recording(
        self, wait: bool, timeout: float = 120.0, success: bool | None = None
    ) -> msg.EpisodeSaved | msg.EpisodeNotSaved | msg.SessionState: ...
    def stop_recording(
        self, wait: bool = True, timeout: float = 120.0, success: bool | None = None
    ) -> msg.EpisodeSaved | msg.EpisodeNotSaved | msg.SessionState:
        """Stop and store; with ``wait`` returns the EpisodeSaved / EpisodeNotSaved outcome.

        ``success`` marks the episode (None: the task's success predicate when recording stops).

        Raises :class:`~studio.backend.bus.RemoteError` if the worker refuses (e.g. too short), in which
        case the recording goes on.
        """
        with self._events_cond:
            seen = len(self.episodes)
        state = self._request(msg.StopRecording(success=success), msg.SessionState)
        if not wait:
            return state
        deadline = time.monotonic() + timeout
        with self._events_cond:
            while len(self.episodes) <= seen:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"the episode was not stored within {timeout} s")
                self._events_cond.wait(left)
            return self.episodes[seen]

    # ------------------------------------------------------------------ images and geometry
    def request_frame(
        self, camera: str = "external", encoding: msg.ImageEncoding = "jpeg", quality: int = 80
    ) -> msg.ImageFrame:
        return self._request(
            msg.RequestFrame(camera=camera, encoding=encoding, quality=quality), msg.ImageFrame
        )

    def stream_frames(
        self, hz: float, camera: str = "external", encoding: msg.ImageEncoding = "jpeg", quality: int = 80
    ) -> None:
        self._request(msg.StreamFrames(camera=camera, hz=hz, encoding=encoding, quality=quality), msg.Ack)

    def geometry(self) -> msg.SceneGeometry:
        return self._request(msg.GetGeometry(), msg.SceneGeometry)

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Close the session on the worker and drop the client's subscriptions and token."""
        with contextlib.suppress(bus.BusError, zenoh.ZError):
            self._request(msg.CloseSession(), msg.Ack, timeout=3.0)
        entities: list[zenoh.Subscriber | zenoh.Publisher | zenoh.LivelinessToken] = [
            *self._subs,
            self._cmd_pub,
            self._token,
        ]
        for entity in entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()

    def __enter__(self) -> TeleopClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
