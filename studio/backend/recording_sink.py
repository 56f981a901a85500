"""The recording side of a teleop session: what is being recorded, and where a finished recording goes.

A :class:`RecordingSink` owns the ticks recorded so far, the recording's role and draft id, and two threads:

* **saver** — hands finished recordings to the store (a shared data directory or the bus); on failure
  the recording is kept as a draft of the data directory (offered back by the Teleop panel's *Interrupted
  recordings*), or, without one, written to the worker's spool directory — never lost.
* **draft** — sends the ticks of a recording that has a *draft* id as
  :class:`~studio.backend.messages.DraftChunk` messages every :data:`DRAFT_PERIOD_S` of simulated time, so a
  client holds them even if this worker dies mid-recording.

Stopping trims a recording started from rest to its active span and hands it back as a
:class:`StoppedRecording`, which the session renders into a :class:`~studio.sim.recording.Recording` on its
render thread and gives back to :meth:`RecordingSink.store`.
"""

from __future__ import annotations

import collections
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import EpisodeDestination, ShipError, recording_payload
from studio.data.atomic_files import atomic_write
from studio.sim.env import Simulator
from studio.sim.recorder import Recorder, active_span
from studio.sim.recording import Recording

#: A recording shorter than this many control ticks is refused (the store wants ≥ 20 frames).
MIN_RECORDED_STEPS = 20
#: Recorded episodes get one video frame per this many seconds of simulated time (10 fps) ...
FRAME_PERIOD_S = 0.1
#: ... but never fewer than MIN_RECORDED_STEPS frames, nor more than this.
MAX_RECORDED_FRAMES = 300
#: A recording with a draft id sends its new ticks at least this often (simulated seconds).
DRAFT_PERIOD_S = 0.1
#: Default robot role of a teleop recording, by robot (the Sawyer and the human hand demonstrate, the Panda is
#: the agent).
DEFAULT_ROLE: dict[str, msg.Role] = {"sawyer": "expert", "panda": "agent", "hand": "expert"}


@dataclass
class StoppedRecording:
    """A stopped recording's ticks and what its episode is stored with, before its frames are rendered."""

    rows: list[dict]
    states: list[np.ndarray]
    task: str
    seed: int
    success: bool
    role: msg.Role
    n_frames: int
    extra: dict
    draft: str | None

    def render(self, env: Simulator) -> Recording:
        """The finished recording, its frames rendered on ``env`` (reset to this recording's task, seed)."""
        rec = Recorder(env)
        rec.rows, rec.states = self.rows, self.states
        return rec.finish(n_frames=self.n_frames, success=self.success)


@dataclass
class _DraftSend:
    draft: str
    first_step: int
    rows: list[dict]
    states: list[np.ndarray]


def _rows_from_arrays(arrays: dict[str, np.ndarray]) -> list[dict]:
    """Recorded arrays (name -> (T, ...)) back to the per-tick rows a Recorder keeps."""
    n = len(arrays["time"])
    return [
        {
            k: (float(v[t]) if np.ndim(v[t]) == 0 else np.asarray(v[t], dtype=np.float64))
            for k, v in arrays.items()
        }
        for t in range(n)
    ]


class RecordingSink:
    """The recording of one teleop session, its draft chunks, and the storing of what it finishes.

    The session calls :meth:`start`, :meth:`tick`, :meth:`stop` and :meth:`discard` on its sim thread;
    ``publish_status`` sends a message on the session's status key and ``session_state`` is the session's
    current :class:`~studio.backend.messages.SessionState`, published after each recording is stored.
    """

    def __init__(
        self,
        zsession: zenoh.Session,
        worker: str,
        session_id: str,
        destination: EpisodeDestination,
        spool_dir: Path,
        drafts_dir: Path | None,
        publish_status: Callable[[msg.Message], None],
        session_state: Callable[[], msg.SessionState],
        role: msg.Role,
        fork: msg.ForkStart | None = None,
    ):
        self.worker = worker
        self.session_id = session_id
        self.destination = destination
        self.spool_dir = spool_dir
        self.drafts_dir = drafts_dir
        self._publish_status = publish_status
        self._session_state = session_state
        self._closed = False
        self._recorder: Recorder | None = None
        self._role: msg.Role = role
        self._extra: dict = {}  # stored with the recording's episode
        self._draft: str | None = None  # the recording's draft id
        self._draft_sent = 0  # ticks of the recording already sent as draft chunks
        self._draft_queue: collections.deque[_DraftSend] = collections.deque()
        self._draft_cond = threading.Condition()
        self._trim_idle = fork is None
        #: Recordings stopped but not yet stored or refused (being rendered, queued or being saved).
        self.saving = 0
        self._saving_lock = threading.Lock()
        self._save_queue: collections.deque[tuple[Recording, StoppedRecording]] = collections.deque()
        self._save_cond = threading.Condition()
        self._draft_pub = zsession.declare_publisher(
            keys.session_key(worker, session_id, "draft"), congestion_control=bus.MUST_ARRIVE
        )
        self.threads = [
            threading.Thread(target=self._save_loop, name=f"save-{session_id}", daemon=True),
            threading.Thread(target=self._draft_loop, name=f"draft-{session_id}", daemon=True),
        ]

    def continue_fork(self, env: Simulator, fork: msg.ForkStart) -> None:
        """Record on from a forked episode: its ticks so far are the recording's first ones."""
        self._recorder = Recorder(env)
        self._recorder.rows = _rows_from_arrays({k: v.to_array() for k, v in fork.arrays.items()})
        self._recorder.states = list(fork.states.to_array())
        self._role = fork.role
        self._extra = {"forked_from": dict(fork.origin)} if fork.origin else {}
        self._draft, self._draft_sent = fork.draft, len(self._recorder.states)

    # ------------------------------------------------------------------ the recording (sim thread)
    @property
    def recording(self) -> bool:
        return self._recorder is not None

    @property
    def recorded_steps(self) -> int | None:
        """Ticks recorded so far, None when not recording."""
        rec = self._recorder
        return None if rec is None else len(rec)

    def start(self, env: Simulator, role: msg.Role | None, draft: str | None) -> None:
        """Start recording ``env`` from its current tick (``role`` None: the robot's default role)."""
        self._role = role or DEFAULT_ROLE.get(env.robot, "expert")
        self._recorder = Recorder(env)
        self._recorder.tick()
        self._extra = {}
        self._trim_idle = True
        self._draft, self._draft_sent = draft, 0

    def tick(self, control_dt: float) -> None:
        """Record the tick just stepped, and queue a draft chunk when one is due."""
        if self._recorder is not None:
            self._recorder.tick()
            if (
                self._draft is not None
                and (len(self._recorder) - self._draft_sent) * control_dt >= DRAFT_PERIOD_S
            ):
                self._queue_draft()

    def stop(self, env: Simulator, task: str, seed: int, success: bool | None) -> StoppedRecording:
        """End the recording (at least :data:`MIN_RECORDED_STEPS` ticks long) and count it as being saved."""
        rec = self._recorder
        assert rec is not None and len(rec) >= MIN_RECORDED_STEPS, "the session checks the recording first"
        # A recording started here is stored from just before its first motion to just after its last; one
        # that continues an episode (a fork, a resumed draft) keeps every tick its draft holds.
        start, end = active_span(rec.rows, env.control_dt) if self._trim_idle else (0, len(rec))
        if end - start < MIN_RECORDED_STEPS:
            start, end = 0, len(rec)
        rows, states = rec.rows[start:end], rec.states[start:end]
        n_frames = int(
            np.clip(
                round(len(rows) * env.control_dt / FRAME_PERIOD_S), MIN_RECORDED_STEPS, MAX_RECORDED_FRAMES
            )
        )
        self._queue_draft()  # the draft holds the whole recording before it is stored
        job = StoppedRecording(
            rows,
            states,
            task,
            seed,
            bool(env.success() if success is None else success),
            self._role,
            n_frames,
            dict(self._extra),
            self._draft,
        )
        self._recorder, self._draft, self._extra = None, None, {}
        with self._saving_lock:
            self.saving += 1
        return job

    def discard(self) -> bool:
        """Drop the recording; False if there was none."""
        if self._recorder is None:
            return False
        self._recorder, self._draft, self._extra = None, None, {}
        return True

    def _queue_draft(self) -> None:
        """Hand the recording's unsent ticks to the draft thread as one draft chunk (sim thread)."""
        rec, draft = self._recorder, self._draft
        if rec is None or draft is None or len(rec) <= self._draft_sent:
            return
        send = _DraftSend(
            draft, self._draft_sent, rec.rows[self._draft_sent :], rec.states[self._draft_sent :]
        )
        self._draft_sent = len(rec)
        with self._draft_cond:
            self._draft_queue.append(send)
            self._draft_cond.notify()

    # ------------------------------------------------------------------ finished recordings (render thread)
    def store(self, recording: Recording, stopped: StoppedRecording) -> None:
        """Queue a rendered recording for the saver thread."""
        with self._save_cond:
            self._save_queue.append((recording, stopped))
            self._save_cond.notify()

    def not_rendered(self, error: Exception) -> None:
        """A stopped recording whose frames could not be rendered: it is not saved, say so."""
        self._saving_done()
        self._publish_status(
            msg.EpisodeNotSaved(session=self.session_id, reason=f"rendering failed: {error}", kept_at="")
        )

    # ------------------------------------------------------------------ saver thread
    def _saving_done(self) -> None:
        with self._saving_lock:
            self.saving = max(0, self.saving - 1)

    def _save_loop(self) -> None:
        while True:
            with self._save_cond:
                while not self._save_queue:
                    # ``saving`` counts a recording from its stop until it is stored or refused, so it also
                    # covers those the session's render thread is still finishing.
                    if self._closed and self.saving == 0:
                        return
                    self._save_cond.wait(0.5)
                recording, finish = self._save_queue.popleft()
            role, more, draft = finish.role, finish.extra, finish.draft
            extra = {"session": self.session_id, "worker": self.worker, **more}
            try:
                episode = self.destination.save(recording, role=role, source="teleop", extra=extra)
                self._saving_done()
                self._publish_status(
                    msg.EpisodeSaved(
                        session=self.session_id,
                        episode=episode,
                        task=recording.task,
                        role=role,
                        steps=recording.num_steps,
                        frames=len(recording.frames),
                        success=bool(recording.success),
                        via=self.destination.via,
                        draft=draft,
                    )
                )
            except ShipError as e:
                self._saving_done()
                self._publish_status(
                    msg.EpisodeNotSaved(
                        session=self.session_id, reason=str(e), kept_at=str(e.kept_at), draft=draft
                    )
                )
            except Exception as e:
                bus.log.error(
                    "session %s: storing a recording failed: %s",
                    self.session_id,
                    bus.one_line(e, with_type=True),
                )
                bus.log.debug("session %s: storing a recording failed", self.session_id, exc_info=True)
                kept = self._rescue(recording, finish, extra)
                self._saving_done()
                self._publish_status(
                    msg.EpisodeNotSaved(
                        session=self.session_id, reason=f"{type(e).__name__}: {e}", kept_at=kept, draft=draft
                    )
                )
            self._publish_status(self._session_state())

    def _draft_loop(self) -> None:
        """Send queued draft chunks, in order (reliably: a chunk is never dropped for a newer one)."""
        while True:
            with self._draft_cond:
                while not self._draft_queue:
                    if self._closed:
                        return
                    self._draft_cond.wait(0.5)
                send = self._draft_queue.popleft()
            try:
                fields = send.rows[0].keys()
                chunk = msg.DraftChunk(
                    session=self.session_id,
                    draft=send.draft,
                    first_step=send.first_step,
                    states=msg.ArrayData.of(np.stack(send.states)),
                    arrays={
                        k: msg.ArrayData.of(np.stack([np.asarray(r[k], dtype=np.float64) for r in send.rows]))
                        for k in fields
                    },
                )
                self._draft_pub.put(msg.encode(chunk))
            except (zenoh.ZError, ValueError) as e:
                bus.log.error("session %s: a draft chunk could not be sent: %s", self.session_id, e)

    def _rescue(self, recording: Recording, finish: StoppedRecording, extra: dict) -> str:
        """Keep a recording the store refused, so nothing is lost: as a draft of the data dir (which the studio's
        Teleop panel offers back under *Interrupted recordings*), else in the spool directory. Returns where."""
        if self.drafts_dir is not None:
            try:
                return self._keep_as_draft(recording, finish, extra)
            except (OSError, ValueError) as e:
                bus.log.error(
                    "session %s: could not keep the recording as a draft: %s",
                    self.session_id,
                    bus.one_line(e),
                )
        try:
            self.spool_dir.mkdir(parents=True, exist_ok=True)
            path = self.spool_dir / f"unsaved-{self.session_id}-{int(time.time() * 1000)}.recording"
            atomic_write(path, msg.encode(recording_payload(recording)))
            return str(path)
        except OSError as e:
            bus.log.error("could not even spool the recording: %s", e)
            return ""

    def _keep_as_draft(self, recording: Recording, finish: StoppedRecording, extra: dict) -> str:
        from studio.data.drafts import DraftError, RecordingDrafts

        assert self.drafts_dir is not None
        drafts = RecordingDrafts(self.drafts_dir)
        n = len(finish.states)
        if finish.draft is not None:  # the client journaled it: kept already if its draft holds every tick
            try:
                if drafts.next_step(finish.draft) >= n:
                    return f"draft {finish.draft} (Teleop: Interrupted recordings)"
            except (DraftError, OSError):
                pass
        draft = f"unsaved-{int(time.time())}-{secrets.token_hex(3)}"
        header = {
            "scene": recording.scene,
            "robot": recording.robot,
            "task": recording.task,
            "seed": int(recording.seed),
            "control_dt": float(recording.control_dt),
            "role": finish.role,
            "forked_from": extra.get("forked_from"),
            "session": self.session_id,
        }
        drafts.create(draft, header)
        try:
            arrays = {
                k: np.stack([np.asarray(r[k], dtype=np.float64) for r in finish.rows]) for k in finish.rows[0]
            }
            drafts.append(draft, 0, np.stack(finish.states), arrays)
        except BaseException:
            drafts.discard(draft)
            raise
        return f"draft {draft} (Teleop: Interrupted recordings)"

    # ------------------------------------------------------------------ closing
    def start_threads(self) -> None:
        for t in self.threads:
            t.start()

    def close(self) -> None:
        """Let the threads end once every stopped recording is stored and every draft chunk sent; join
        :attr:`threads` to wait for that."""
        self._closed = True
        with self._save_cond:
            self._save_cond.notify_all()
        with self._draft_cond:
            self._draft_cond.notify_all()

    def undeclare(self) -> None:
        try:
            self._draft_pub.undeclare()
        except zenoh.ZError:
            pass
