"""Continuing recorded episodes in a teleop session: forks of stored rollouts, and drafts of interrupted recordings.

*Fork* — :func:`fork_rollout` turns ticks 0 … k of a stored rollout into the
:class:`~studio.backend.messages.ForkStart` of a session: the worker restores tick k exactly and records on,
the rollout's ticks included, and the saved episode says ``forked_from`` (rollout, step, its recording).

*Drafts* — every recording the studio starts has a draft id; :class:`DraftKeeper` appends the session's
:class:`~studio.backend.messages.DraftChunk` messages to ``<data-dir>/drafts/`` as they arrive. If the sim
worker dies mid-recording, :func:`resume_draft` continues the draft on another worker from its last tick,
and when the episode is stored the draft is deleted.
"""

from __future__ import annotations

import logging
import secrets
import threading
from dataclasses import dataclass

from studio.backend import messages as msg
from studio.data.drafts import Draft, DraftError, RecordingDrafts
from studio.data.forks import ForkSource, fork_source

log = logging.getLogger("studio.forking")


def new_draft_id() -> str:
    return f"d-{secrets.token_hex(6)}"


def _start(draft: str, states, arrays, gripper: float, control_dt: float, role: msg.Role, origin: dict):
    return msg.ForkStart(
        draft=draft,
        states=msg.ArrayData.of(states),
        arrays={k: msg.ArrayData.of(v) for k, v in arrays.items()},
        gripper=gripper,
        control_dt=control_dt,
        role=role,
        origin=origin,
    )


@dataclass(frozen=True)
class Continuation:
    """What :meth:`~studio.backend.teleop_client.TeleopClient.open` needs to continue an episode."""

    scene: str
    robot: str
    task: str
    seed: int
    fork: msg.ForkStart

    @property
    def steps(self) -> int:
        return int(self.fork.states.shape[0])


def fork_rollout(store, drafts: RecordingDrafts, rollout_id: str, step: int, role: msg.Role) -> Continuation:
    """A new draft continuing rollout ``rollout_id`` at tick ``step``; raises ValueError with the reason."""
    src: ForkSource = fork_source(store, rollout_id, step)
    draft = new_draft_id()
    drafts.create(
        draft,
        {
            "scene": src.scene,
            "robot": src.robot,
            "task": src.task,
            "seed": src.seed,
            "control_dt": src.control_dt,
            "role": role,
            "prefix": {"rollout": rollout_id, "steps": src.step + 1},
            "forked_from": src.origin,
        },
    )
    fork = _start(draft, src.states, src.arrays, src.gripper, src.control_dt, role, src.origin)
    return Continuation(src.scene, src.robot, src.task, src.seed, fork)


def resume_draft(store, drafts: RecordingDrafts, draft_id: str) -> Continuation:
    """Continue draft ``draft_id`` from its last journaled tick (its chunks keep going to the same draft)."""
    d: Draft = drafts.load(draft_id, store)
    h = d.header
    role: msg.Role = "expert" if h["role"] == "expert" else "agent"
    fork = _start(
        d.id, d.states, d.arrays, d.gripper, float(h["control_dt"]), role, h.get("forked_from") or {}
    )
    return Continuation(str(h["scene"]), str(h["robot"]), str(h["task"]), int(h["seed"]), fork)


class DraftKeeper:
    """Appends one client's draft chunks to the drafts of a data directory (thread-safe, in arrival order).

    A chunk that does not fit its draft (a gap) is logged and remembered in :attr:`broken`: the draft then
    ends where the gap starts, and resuming it continues from there.
    """

    def __init__(self, drafts: RecordingDrafts):
        self.drafts = drafts
        self.broken: dict[str, str] = {}
        self.kept: dict[str, int] = {}  # draft -> ticks appended by this keeper
        self._lock = threading.Lock()

    def __call__(self, chunk: msg.DraftChunk) -> None:
        with self._lock:
            if chunk.draft in self.broken:
                return
            try:
                n = self.drafts.append(
                    chunk.draft,
                    chunk.first_step,
                    chunk.states.to_array(),
                    {k: v.to_array() for k, v in chunk.arrays.items()},
                )
                self.kept[chunk.draft] = self.kept.get(chunk.draft, 0) + n
            except (DraftError, OSError, ValueError) as e:
                self.broken[chunk.draft] = str(e)
                log.error("draft %s: %s", chunk.draft, e)
