"""Scripted Meta-World experts: each task's policy from ``metaworld.policies``, recorded like our own experts.

A policy reads Meta-World's observation (:meth:`MetaWorldEnv.observation`) and answers with a delta
action (dx, dy, dz, grab effort in [-1, 1]). We apply it with :meth:`MetaWorldEnv.step_action`, which
does to the simulation exactly what Meta-World's ``step`` does (mocap moved by action × 1 cm per axis,
finger controls ± effort) without its 500-step episode bookkeeping, so the policies succeed as often as
in Meta-World itself. The recorded gripper command is the effort on our 0 (open) … 1 (closed) scale,
``(effort + 1) / 2``: policies that close the fingers command 0.8–1.0, pressing and pushing ones hold
0.5 (effort 0) or 0 (effort −1); a binary label is ``gripper_cmd > 0.5``. Making the effort binary
instead breaks several policies (assembly, basketball, pick-out-of-hole, peg-unplug-side fail almost
always; measured in ``docs/metaworld.md``).

An episode stops :data:`AFTER_SUCCESS` ticks after the env's success signal first comes on (the
reference data kept 5) and fails after :data:`MAX_TICKS` (Meta-World's horizon). Failed episodes are
returned with ``success=False``; collection discards them.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from studio.sim.metaworld_env import IMAGE_SIZE, MetaWorldEnv
from studio.sim.metaworld_tasks import SCENE, get_metaworld_task
from studio.sim.recorder import Recorder
from studio.sim.recording import Recording

AFTER_SUCCESS = 5
MAX_TICKS = 500


def scripted_policy(task: str):
    """A fresh instance of the ``metaworld.policies`` policy of ``task`` (``metaworld/<v3 name>``)."""
    from metaworld.policies import ENV_POLICY_MAP

    # The map's values are concrete subclasses of the abstract Policy its type names (mypy would refuse to
    # instantiate a type[Policy]).
    policy_cls: Callable[[], Any] = ENV_POLICY_MAP[get_metaworld_task(task).env_name]
    return policy_cls()


def expert_action(policy, env: MetaWorldEnv) -> np.ndarray:
    """The policy's action (dx, dy, dz, grab effort) for the env's current state."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the policies warn whenever their P-gain saturates an axis
        return np.asarray(policy.get_action(env.observation()), dtype=np.float64)


def run_expert(
    env: MetaWorldEnv,
    recorder: Recorder | None = None,
    max_ticks: int = MAX_TICKS,
    after_success: int = AFTER_SUCCESS,
) -> int | None:
    """Run the scripted policy on the env's current episode; the tick of first success, or None."""
    if env.task is None:
        raise RuntimeError("run_expert: reset the env to the task's episode first")
    policy = scripted_policy(env.task.name)
    first = None
    for _ in range(max_ticks):
        env.step_action(expert_action(policy, env))
        if recorder is not None:
            recorder.tick()
        if first is None and env.success_now():
            first = env.steps
        if first is not None and env.steps >= first + after_success:
            break
    return first


def record_expert(
    scene: str,
    robot: str,
    task: str,
    seed: int,
    image_size: tuple[int, int] = IMAGE_SIZE,
    min_frames: int = 30,
    env: MetaWorldEnv | None = None,
) -> Recording:
    """One scripted Meta-World episode, recorded: full-rate arrays and ``min_frames`` evenly spaced frames.

    Same signature as :func:`studio.sim.experts.record_expert`; ``scene`` must be ``"metaworld"`` and
    ``robot`` ``"sawyer"``. Pass ``env`` to reuse an environment across episodes.
    """
    if scene != SCENE:
        raise ValueError(f"the Meta-World experts record scene {SCENE!r}, not {scene!r}")
    size = (int(image_size[0]), int(image_size[1]))
    if env is not None and env.image_size != size:
        raise ValueError(f"env renders {env.image_size}, the recording asks for {size}")
    own = env is None
    env = env or MetaWorldEnv(scene, robot, image_size=size)
    try:
        env.reset(task, seed)
        rec = Recorder(env)
        rec.tick()
        first = run_expert(env, rec)
        return rec.finish(n_frames=min_frames, success=first is not None)
    finally:
        if own:
            env.close()


ORACLE_SETTLE = 10
"""Ticks after first success at which :func:`expert_waypoints` ends its path: success thresholds are tight, and a
plan ending exactly where the signal first came on stops short by the waypoint controller's tolerance."""


GRASP_WINDOW = 30
"""Ticks after the policy first closes the fingers in which :func:`expert_waypoints` looks for the grasp's bottom."""


def expert_waypoints(
    task: str, seed: int, n: int = 5, scratch: MetaWorldEnv | None = None, strict: bool = False
) -> np.ndarray:
    """(n, 4) waypoints [x, y, z, gripper] of the scripted policy's own episode of (task, seed).

    The policy runs in a scratch environment (``scratch``, or a small one made and closed here) from the same
    reset until :data:`ORACLE_SETTLE` ticks after its first success; the waypoints are ``n`` hand positions evenly
    spaced in time after the start, closed where the policy's grab effort is positive. This is the Meta-World
    oracle of ``studio eval --checkpoint oracle``: the ceiling of five waypoints executed by our controller, not
    a model. The scripted policies fail on a few seeds (98.4 % success, ``docs/metaworld.md``); then the path is the
    policy's whole failed attempt (:data:`MAX_TICKS`), as a ceiling should count it — or, with ``strict``, a
    RuntimeError.
    """
    own = scratch is None
    env = scratch or MetaWorldEnv(image_size=(32, 32))
    try:
        env.reset(task, seed)
        policy = scripted_policy(task)
        hand_path: list[np.ndarray] = []
        closed_path: list[float] = []
        first = None
        for _ in range(MAX_TICKS):
            action = expert_action(policy, env)
            env.step_action(action)
            hand_path.append(env.ee_pos.copy())
            closed_path.append(float(action[3] > 0))
            if first is None and env.success_now():
                first = env.steps
            if first is not None and env.steps >= first + ORACLE_SETTLE:
                break
        if first is None and strict:
            raise RuntimeError(f"the scripted policy of {task} failed on seed {seed}")
        hand, closed = np.asarray(hand_path), np.asarray(closed_path)
        idx = np.round(np.linspace(0, len(hand) - 1, n + 1)[1:]).astype(int)
        closes = np.flatnonzero(np.diff(closed, prepend=0.0) > 0)
        if len(closes) and n > 1:
            # The policies close the fingers while still descending; our controller closes on arrival, so the
            # grasp waypoint is the lowest hand point of the next GRASP_WINDOW ticks, open until there.
            first = int(closes[0])
            grasp = first + int(np.argmin(hand[first : first + GRASP_WINDOW, 2]))
            closed[first:grasp] = 0.0
            k = int(np.argmin(np.abs(idx[:-1] - grasp)))
            idx[k] = grasp
            idx = np.sort(idx)
        return np.column_stack([hand[idx], closed[idx]])
    finally:
        if own:
            env.close()
