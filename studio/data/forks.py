"""Forking a stored rollout: its per-tick physics states, and the start of an episode continued from a tick.

A rollout keeps, beside its plans, the MuJoCo integration state of every control tick
(``<rollout-dir>/states.npz``). :func:`fork_source` gathers what a teleop session needs to continue that
rollout from tick ``step`` exactly as it was — the states and recorded arrays of ticks 0 … ``step``, the
gripper command then, the control period — and says clearly why a rollout cannot be forked.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: A rollout directory's file of per-tick physics states.
STATES_FILE = "states.npz"


def write_states(folder: str | os.PathLike, states: np.ndarray) -> None:
    """Write a rollout's (T, S) float64 physics states into ``folder`` (which is still being assembled)."""
    np.savez_compressed(Path(folder) / STATES_FILE, states=np.asarray(states, dtype=np.float64))


def read_states(folder: str | os.PathLike) -> np.ndarray | None:
    """The (T, S) physics states stored in a rollout directory, or None if it has none."""
    path = Path(folder) / STATES_FILE
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as data:
        return np.asarray(data["states"], dtype=np.float64)


@dataclass(frozen=True)
class ForkSource:
    """Ticks 0 … ``step`` of a stored rollout: what a session restores and records on from."""

    rollout_id: str
    step: int
    episode_id: str
    scene: str
    robot: str
    task: str
    seed: int
    control_dt: float
    states: np.ndarray  # (step + 1, S) float64
    arrays: dict[str, np.ndarray]  # each (step + 1, ...)
    object_names: tuple[str, ...]

    @property
    def gripper(self) -> float:
        """The gripper command in force at ``step``."""
        return float(np.clip(self.arrays["gripper_cmd"][-1], 0.0, 1.0))

    @property
    def origin(self) -> dict:
        """What the continued episode stores as ``forked_from``."""
        return {"rollout": self.rollout_id, "step": self.step, "episode": self.episode_id}


class CannotFork(ValueError):
    """A rollout (or tick) that cannot be continued; the message says why."""


def fork_source(store, rollout_id: str, step: int) -> ForkSource:
    """Ticks 0 … ``step`` of rollout ``rollout_id`` in ``store``; raises :class:`CannotFork` with the reason."""
    record = store.catalog.get_rollout(rollout_id)
    if record is None:
        raise CannotFork(f"no rollout {rollout_id!r} in {store.root}")
    if record.episode_id is None or record.path is None:
        raise CannotFork(
            f"rollout {rollout_id} was stored without its recording (eval --no-keep): nothing to fork"
        )
    states = read_states(record.path)
    if states is None:
        raise CannotFork(
            f"rollout {rollout_id} was stored without its physics states (by a studio that did not keep "
            "them): it can be replayed but not continued exactly"
        )
    try:
        meta = store.get(record.episode_id)
        _, _, arrays = store.load_arrays(record.episode_id)
    except (KeyError, FileNotFoundError, OSError, ValueError) as e:
        raise CannotFork(
            f"rollout {rollout_id}'s recording {record.episode_id} cannot be read: {e}"
        ) from None
    n = len(states)
    if any(len(a) != n for a in arrays.values()):
        raise CannotFork(
            f"rollout {rollout_id}: {n} physics states but {len(arrays['time'])} recorded ticks; its files "
            "do not belong together"
        )
    if not 0 <= int(step) < n:
        raise CannotFork(f"rollout {rollout_id} has ticks 0 … {n - 1}; cannot fork at tick {step}")
    k = int(step) + 1
    if meta.seed is None or meta.control_dt is None:
        raise CannotFork(f"rollout {rollout_id}'s recording has no seed or control period")
    return ForkSource(
        rollout_id=rollout_id,
        step=int(step),
        episode_id=record.episode_id,
        scene=meta.scene,
        robot=meta.embodiment,
        task=meta.task,
        seed=int(meta.seed),
        control_dt=float(meta.control_dt),
        states=states[:k].copy(),
        arrays={name: np.asarray(a[:k]) for name, a in arrays.items()},
        object_names=tuple(meta.object_names),
    )
