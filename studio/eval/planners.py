"""Getting a planner for a checkpoint path or ``"oracle"``, and the per-process cache that keeps models loaded.

A sim worker runs many rollout and plan jobs; loading a model for each would cost seconds, so planners (and
anything else a worker process wants once, e.g. its episode store) live in :func:`process_cached` for the
life of the process. A checkpoint plans only the scene it was trained on (the scene of the tasks its file
records): asked for another scene's task, :func:`load_planner` refuses with the reason instead of planning.

Every process that plans with a model uses :data:`PLANNING_THREADS` torch threads, whatever else runs beside it:
a plan made with 1 and with 2 threads differs by ~5·10⁻⁸ (sums split differently), which can tip a rollout, so a
thread count that followed the number of evaluation workers made the same (checkpoint, task, seed, demonstration)
a different rollout under ``--workers 1`` and ``--workers 2``.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

from studio.eval.oracle import OraclePlanner
from studio.model.checkpoint_info import checkpoint_scene
from studio.sim.env import SimEnv

T = TypeVar("T")

#: torch intra-op threads of a process that plans (evaluation workers, sim workers): fixed, so that a rollout is
#: bit-identical whichever process runs it.
PLANNING_THREADS = 1

_CACHE: dict[Hashable, Any] = {}


def process_cached(key: Hashable, make: Callable[[], T]) -> T:
    """The value cached under ``key`` in this process, made with ``make()`` the first time it is asked for."""
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


def use_planning_threads() -> int:
    """Set this process's torch intra-op threads to :data:`PLANNING_THREADS`; returns the count before."""
    import torch

    before = torch.get_num_threads()
    if before != PLANNING_THREADS:
        torch.set_num_threads(PLANNING_THREADS)
    return before


def load_planner(checkpoint: str, env: SimEnv):
    """An :class:`~studio.eval.oracle.OraclePlanner` on ``env`` for ``"oracle"``, else the checkpoint's
    :class:`~studio.model.planner.Planner` (loaded once per process and path), planning on
    :data:`PLANNING_THREADS` threads. Raises ``ValueError`` for a checkpoint trained on another scene than
    ``env``'s."""
    if checkpoint == "oracle":
        return OraclePlanner(env)
    scene = checkpoint_scene(checkpoint)
    if scene is not None and scene != env.scene:
        raise ValueError(f"{checkpoint} was trained on {scene} tasks: it does not plan {env.scene} tasks")

    def make():
        from studio.model.planner import Planner  # torch: loaded by the first job that needs a model

        return Planner.load(checkpoint)

    use_planning_threads()
    return process_cached(("planner", checkpoint), make)
