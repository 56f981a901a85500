"""Getting a planner for a checkpoint path or ``"oracle"``, and the per-process cache that keeps models loaded.

A sim worker runs many rollout and plan jobs; loading a model for each would cost seconds, so planners (and
anything else a worker process wants once, e.g. its episode store) live in :func:`process_cached` for the
life of the process. A checkpoint plans only the scene it was trained on (the scene of the tasks its file
records): asked for another scene's task, :func:`load_planner` refuses with the reason instead of planning.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

from studio.eval.oracle import OraclePlanner
from studio.model.checkpoint_info import checkpoint_scene
from studio.sim.env import SimEnv

T = TypeVar("T")

_CACHE: dict[Hashable, Any] = {}


def process_cached(key: Hashable, make: Callable[[], T]) -> T:
    """The value cached under ``key`` in this process, made with ``make()`` the first time it is asked for."""
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


def load_planner(checkpoint: str, env: SimEnv):
    """An :class:`~studio.eval.oracle.OraclePlanner` on ``env`` for ``"oracle"``, else the checkpoint's
    :class:`~studio.model.planner.Planner` (loaded once per process and path). Raises ``ValueError`` for a
    checkpoint trained on another scene than ``env``'s."""
    if checkpoint == "oracle":
        return OraclePlanner(env)
    scene = checkpoint_scene(checkpoint)
    if scene is not None and scene != env.scene:
        raise ValueError(f"{checkpoint} was trained on {scene} tasks: it does not plan {env.scene} tasks")

    def make():
        from studio.model.planner import Planner  # torch: loaded by the first job that needs a model

        return Planner.load(checkpoint)

    return process_cached(("planner", checkpoint), make)
