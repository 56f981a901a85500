"""The ``collect`` job of a sim worker: scripted episodes in bulk, as ``studio collect``, with progress and cancel.

The Data tab's *Collect scripted episodes* submits it. A thin handler: the collection is
:func:`studio.data.collect.collect` (the same slots, seeds, retries and store as ``studio collect``), run in the
worker's own process (one worker, one job at a time). Its spec (:class:`CollectJobSpec`) is typed and bounded and
:func:`check_spec` validates it on arrival — the worker refuses a bad one before simulating anything, with one line
naming the field (``collect job spec: episodes: …``); the browser runs the same check before it submits.

Progress is "episode i of N" (N = tasks × episodes per task; slots a previous run already filled count as done),
with the counts as metrics. Cancelling stops between episodes: every episode is stored whole or not at all, those
stored stay stored, and the result (published for a cancelled job too) says how many were left. Because each slot's
scene seed is derived from (seed, robot, role, task, index), running the same spec again — or re-queueing the job
after its worker died — only makes the episodes still missing. Episodes go to the worker's ``--data-dir`` store, as
for the ``expert`` and ``rollout`` jobs (the embedded workers share the hub's data directory; a worker whose data
directory is its own then adds each new episode to the hub's store, :mod:`studio.backend.artifact_transfer`).
"""

from __future__ import annotations

import re
import typing
from typing import Annotated, Any, Literal

import msgspec

from studio.backend.job_runner import JobContext

#: Bounds of a collect job: episodes per task, tasks, and the base seed.
MAX_EPISODES = 200
MAX_TASKS = 64
MAX_SEED = 2**31 - 1

Robot = Literal["sawyer", "panda", "hand"]


class CollectJobSpec(msgspec.Struct, forbid_unknown_fields=True):
    """What a ``collect`` job makes (the options of ``studio collect`` a browser may set).

    Attributes:
        scene: scene family (``pick_place``, ``push``, ``metaworld``).
        robot: ``sawyer`` and ``hand`` demonstrate (the hand's episodes have embodiment ``human``), ``panda``
            imitates unless ``role`` is ``expert``; Meta-World has only the Sawyer.
        role: ``expert`` or ``agent``; None: the robot's (:data:`studio.data.collect.ROLE_OF_ROBOT`). The hand
            only demonstrates.
        tasks: task names of the scene (held-out ones included, as ``studio collect`` allows), or the split words
            ``all`` / ``train`` / ``held-out``; after :func:`check_spec`, the task names they stand for.
        episodes: episodes per task, 1 to :data:`MAX_EPISODES`.
        seed: base seed of the run, 0 to :data:`MAX_SEED` (same seed again: only the missing episodes are made).
    """

    tasks: Annotated[
        list[Annotated[str, msgspec.Meta(min_length=1, max_length=200)]],
        msgspec.Meta(min_length=1, max_length=MAX_TASKS),
    ]
    scene: Annotated[str, msgspec.Meta(min_length=1, max_length=64)] = "pick_place"
    robot: Robot = "sawyer"
    role: Literal["expert", "agent"] | None = None
    episodes: Annotated[int, msgspec.Meta(ge=1, le=MAX_EPISODES)] = 10
    seed: Annotated[int, msgspec.Meta(ge=0, le=MAX_SEED)] = 0

    @property
    def total(self) -> int:
        return len(self.tasks) * self.episodes


class SpecError(ValueError):
    """A collect job spec that cannot run; the message is one line naming the field."""

    def __init__(self, field: str, problem: str):
        self.field = field
        super().__init__(f"collect job spec: {field}: {problem}")


def _msgspec_error(raw: Any, e: msgspec.ValidationError) -> SpecError:
    """msgspec's ``Expected `int` <= 200 - at `$.episodes``` as ``episodes: expected `int` <= 200, got …``."""
    text = str(e)
    problem, _, where = text.partition(" - at `$")
    field = where.rstrip("`").lstrip(".")
    missing = re.search(r"missing required field `([^`]+)`", text)
    unknown = re.search(r"unknown field `([^`]+)`", text)
    if missing:
        return SpecError(missing.group(1), "required")
    if unknown:
        return SpecError(
            unknown.group(1), f"not a field of a collect job ({', '.join(CollectJobSpec.__struct_fields__)})"
        )
    if not field:
        return SpecError("(spec)", f"{problem[:1].lower()}{problem[1:]}")
    problem = f"{problem[:1].lower()}{problem[1:]}"
    if field in _CHOICES:
        return SpecError(field, f"{problem}; one of {', '.join(_CHOICES[field])}")
    if "got" not in problem:
        value: Any = raw
        for part in re.findall(r"[^.\[\]]+", field):
            try:
                value = value[int(part)] if isinstance(value, list) else value[part]
            except (KeyError, IndexError, ValueError, TypeError):
                break
        shown = repr(value)
        problem += f", got {shown if len(shown) <= 60 else shown[:57] + '...'}"
    return SpecError(field, problem)


_CHOICES = {"robot": typing.get_args(Robot), "role": ("expert", "agent", "null (the robot's)")}


def check_spec(raw: Any) -> CollectJobSpec:
    """The spec, typed, bounded and checked against the scene; its ``tasks`` resolved to task names.

    Raises :class:`SpecError` (a ValueError) with one line naming the bad field: an unknown or missing field, a
    value out of bounds (``episodes`` 1..200, ``seed`` ≥ 0), a scene without tasks, a robot the scene or role
    does not allow, a task that is not the scene's (another scene's, or unknown).
    """
    from studio.data.collect import ROLE_OF_ROBOT
    from studio.data.splits import resolve_tasks
    from studio.sim.tasks import list_tasks

    try:
        spec = msgspec.convert(raw, CollectJobSpec)
    except msgspec.ValidationError as e:
        raise _msgspec_error(raw, e) from None
    if not list_tasks(spec.scene):
        scenes = sorted({t.split("/", 1)[0] for t in list_tasks()})
        raise SpecError("scene", f"{spec.scene!r} has no tasks; scenes: {', '.join(scenes)}")
    if spec.scene == "metaworld" and spec.robot != "sawyer":
        raise SpecError("robot", f"Meta-World has only the Sawyer, got {spec.robot!r}")
    if spec.robot == "hand" and spec.role == "agent":
        raise SpecError("role", "the human hand only demonstrates: use role 'expert'")
    try:
        tasks = resolve_tasks(spec.scene, spec.tasks)
    except ValueError as e:
        raise SpecError("tasks", str(e)) from None
    if len(tasks) > MAX_TASKS:
        raise SpecError("tasks", f"at most {MAX_TASKS} tasks per job, got {len(tasks)}")
    return msgspec.structs.replace(spec, tasks=tasks, role=spec.role or ROLE_OF_ROBOT[spec.robot])


def run_collect_job(ctx: JobContext) -> dict[str, Any]:
    """Collect as the spec says (:class:`CollectJobSpec`) into the worker's store.

    Returns the run's counts: ``requested`` (tasks × episodes), ``already_present``, ``made``, ``failed_attempts``
    (scripted attempts that failed and were discarded), ``missing`` (slots that failed every attempt, ``task #i``),
    ``left`` (not tried because the job was cancelled), ``stopped``, ``errors``, ``seconds``, and the spec's
    resolved ``scene``, ``robot``, ``role``, ``embodiment``, ``tasks``, ``episodes``, ``seed``.
    """
    spec = check_spec(ctx.spec)
    if ctx.data_dir is None:
        raise ValueError(
            "collect jobs need a worker started with --data-dir (the store to add the episodes to)"
        )
    from studio.data.collect import CollectConfig, SlotDone, collect, missing_slots
    from studio.data.store import EpisodeStore
    from studio.eval.planners import process_cached

    cfg = CollectConfig(
        scene=spec.scene,
        robot=spec.robot,
        role=spec.role,
        tasks=list(spec.tasks),
        episodes=spec.episodes,
        seed=spec.seed,
        workers=1,
        data_dir=str(ctx.data_dir),
        progress=False,
    )
    store = process_cached(("store", str(ctx.data_dir)), lambda: EpisodeStore(ctx.data_dir))
    total = spec.total
    present = total - len(missing_slots(store, cfg, list(spec.tasks)))
    who = f"{spec.robot} {spec.role}"
    ctx.progress(
        present,
        total,
        message=(
            f"starting: {total - present} {who} episodes to make"
            + (f", {present} already stored" if present else "")
        ),
    )

    def on_slot(s: SlotDone) -> None:
        what = "stored" if s.stored else "failed every attempt"
        ctx.progress(
            s.already_present + s.done,
            s.requested,
            message=f"episode {s.already_present + s.done} of {s.requested}: {s.task} #{s.index} {what}",
            made=s.made,
            already_present=s.already_present,
            failed_attempts=s.failed_attempts,
            missing=s.missing,
        )

    before = {m.id for m in store.episodes()}
    result = collect(cfg, on_slot=on_slot, should_stop=lambda: ctx.cancelled)
    for meta in store.episodes():  # to the hub's store, when the worker's data dir is its own
        if meta.id not in before:
            ctx.output_episode(meta.id)
    if result.errors and result.made == 0 and not result.stopped:
        raise RuntimeError(f"no episode could be made: {result.errors[0]}")
    return {
        "scene": spec.scene,
        "robot": spec.robot,
        "role": spec.role,
        "embodiment": cfg.embodiment,
        "tasks": list(spec.tasks),
        "episodes": spec.episodes,
        "seed": spec.seed,
        "requested": result.requested,
        "already_present": result.already_present,
        "made": result.made,
        "failed_attempts": result.failed_attempts,
        "missing": [f"{t} #{i}" for t, i in result.missing[:50]],
        "left": result.left,
        "stopped": result.stopped,
        "errors": result.errors[:10],
        "seconds": result.seconds,
    }
