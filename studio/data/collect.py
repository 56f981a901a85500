"""Scripted collection in bulk: ``studio collect`` runs the scripted experts in parallel into the store.

A collection run is the set of slots (task, index) for index < ``--episodes``, for one robot and one base
seed. Each slot's seed is derived from (base seed, robot, task, index, attempt) by hashing, so a run is
deterministic whatever the number of workers or the order they finish in, and an interrupted run resumes
by making only the slots the catalog does not have yet. Failed scripted episodes are not kept: a slot is
retried with the next attempt's seed, up to ``--max-attempts`` times, and the failures are counted.

The robot decides the role unless ``--role`` says otherwise: the Sawyer and the simulated human hand demonstrate
(``expert``; the hand's episodes are stored with embodiment ``human``, beside uploaded videos of people), the Panda
imitates (``agent``) or, with ``--role expert``, demonstrates for a Panda agent (Two-Franka). A human hand only
demonstrates. The role is part of a slot, so a Panda expert run and a Panda agent run with the same base seed fill
different slots; their scene seeds differ too.
Meta-World (``--scene metaworld``) has only the Sawyer and its own scripted policies
(:mod:`studio.sim.metaworld_experts`); as in the paper, expert and agent come from the same pool, so its
episodes are stored once, as role ``expert`` with embodiment ``sawyer``, and the training view pairs the
pool with itself (``PairDataset(..., scene="metaworld")`` does so by default).
Frames are rendered only for the stored frames (``--min-frames``, ≥ 20), arrays at the full control rate.

:func:`collect` also serves the ``collect`` job of a sim worker (:mod:`studio.backend.collect_job`, the Data tab's
*Collect scripted episodes*): ``on_slot`` hears of every slot done and ``should_stop`` ends the run between slots
(an episode is stored whole or not at all, so stopping leaves no half-written one; running again resumes).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import inspect
import multiprocessing as mp
import os
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from studio.data.paths import add_data_dir_argument
from studio.data.splits import resolve_tasks
from studio.data.store import EpisodeStore, StoreError

if TYPE_CHECKING:
    from studio.sim.recording import Recording

# Headless rendering; must be set before anything imports mujoco (studio.sim.tasks does, via its scenes).
os.environ.setdefault("MUJOCO_GL", "egl")

#: The role a robot's episodes take unless the run says otherwise.
ROLE_OF_ROBOT = {"sawyer": "expert", "panda": "agent", "hand": "expert"}
ROLES = ("expert", "agent")
DEFAULT_RECORDER = "studio.sim.experts:record_expert"
#: Scenes whose scripted experts are not :data:`DEFAULT_RECORDER`.
RECORDER_OF_SCENE = {"metaworld": "studio.sim.metaworld_experts:record_expert"}
MIN_FRAMES = 20


@dataclass
class CollectConfig:
    """One collection run.

    Attributes:
        tasks: full task names, or ``["all"]`` / ``["train"]`` / ``["test"]`` for the scene's tasks or its split.
        image_size: (H, W) of the stored frames; None: the scene's default (240×320, Meta-World 224×224).
        recorder: ``"module:function"`` with the signature of :func:`studio.sim.experts.record_expert`;
            None: the scene's scripted experts.
        role: ``"expert"`` or ``"agent"``; None: the robot's (:data:`ROLE_OF_ROBOT`).
    """

    scene: str = "pick_place"
    robot: str = "sawyer"
    role: str | None = None
    tasks: list[str] = field(default_factory=lambda: ["all"])
    episodes: int = 100
    workers: int = 1
    seed: int = 0
    image_size: tuple[int, int] | None = None
    min_frames: int = 20
    max_attempts: int = 5
    data_dir: str | None = None
    recorder: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.robot not in ROLE_OF_ROBOT:
            raise ValueError(f"robot must be one of {sorted(ROLE_OF_ROBOT)}, got {self.robot!r}")
        if self.role is None:
            self.role = ROLE_OF_ROBOT[self.robot]
        if self.role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {self.role!r}")
        if self.robot == "hand" and self.role != "expert":
            raise ValueError("the human hand only demonstrates: collect it with role 'expert'")
        if self.episodes < 1 or self.workers < 1 or self.max_attempts < 1:
            raise ValueError("episodes, workers and max_attempts must be at least 1")
        if self.min_frames < MIN_FRAMES:
            raise ValueError(f"episodes store at least {MIN_FRAMES} frames, got min_frames={self.min_frames}")
        if self.scene == "metaworld" and self.robot != "sawyer":
            raise ValueError(
                "Meta-World has only the Sawyer: collect with --robot sawyer (its episodes serve as "
                "both expert and agent)"
            )
        if self.image_size is None:
            from studio.sim.env import default_image_size

            self.image_size = default_image_size(self.scene)
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        if self.recorder is None:
            self.recorder = RECORDER_OF_SCENE.get(self.scene, DEFAULT_RECORDER)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(H, W) of the stored frames: ``image_size``, which creation resolved to the scene's default if None."""
        assert self.image_size is not None, "CollectConfig.__post_init__ sets image_size"
        return self.image_size

    @property
    def episode_role(self) -> str:
        """``role``, which creation resolved to the robot's if None."""
        assert self.role is not None, "CollectConfig.__post_init__ sets role"
        return self.role

    @property
    def embodiment(self) -> str:
        """The embodiment the episodes are stored under (``"human"`` for the hand)."""
        from studio.sim.recording import embodiment_of

        return embodiment_of(self.robot)

    @property
    def seed_key(self) -> str:
        """What names the run in :func:`episode_seed`: the robot, with the role when it is not the robot's own
        (so a Panda expert run does not replay the scenes of the Panda agent run with the same base seed)."""
        return self.robot if self.episode_role == ROLE_OF_ROBOT[self.robot] else f"{self.robot}:{self.role}"

    @property
    def recorder_spec(self) -> str:
        """``recorder``, which creation resolved to the scene's scripted experts if None."""
        assert self.recorder is not None, "CollectConfig.__post_init__ sets recorder"
        return self.recorder


@dataclass
class CollectResult:
    """What a collection run did. ``missing`` slots failed every attempt (or raised) and are still empty."""

    requested: int
    already_present: int
    made: int
    failed_attempts: int
    missing: list[tuple[str, int]]
    errors: list[str]
    seconds: float
    stopped: bool = False
    """``should_stop`` ended the run before every slot was tried."""

    @property
    def left(self) -> int:
        """Slots not tried because the run was stopped."""
        return self.requested - self.already_present - self.made - len(self.missing)

    @property
    def episodes_per_min(self) -> float:
        return 60.0 * self.made / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        text = (
            f"collected {self.made} episodes in {self.seconds:.1f} s ({self.episodes_per_min:.1f}/min); "
            f"{self.already_present} were already present; {self.failed_attempts} scripted attempts failed "
            f"and were discarded"
        )
        if self.missing:
            text += f"; {len(self.missing)} slots still missing (run again to retry)"
        if self.stopped:
            text += f"; stopped with {self.left} slots not tried (run again to continue)"
        return text


@dataclass(frozen=True)
class SlotDone:
    """What :func:`collect` tells ``on_slot`` after each slot: the slot, and the run so far.

    ``done`` counts the slots tried of ``todo`` (the slots the catalog did not have when the run started);
    ``requested`` = tasks × episodes = ``already_present`` + ``todo``.
    """

    task: str
    index: int
    stored: bool
    done: int
    todo: int
    requested: int
    already_present: int
    made: int
    failed_attempts: int
    missing: int


def episode_seed(base_seed: int, robot: str, task: str, index: int, attempt: int = 0) -> int:
    """The scene seed of one slot and attempt (31-bit, stable across processes and Python versions); ``robot`` is
    the run's :attr:`CollectConfig.seed_key`."""
    digest = hashlib.sha256(f"{base_seed}|{robot}|{task}|{index}|{attempt}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def missing_slots(store: EpisodeStore, cfg: CollectConfig, tasks: list[str]) -> list[tuple[str, int]]:
    """Slots of the run without an episode in the catalog, task by task, index by index."""
    out: list[tuple[str, int]] = []
    for task in tasks:
        have = store.catalog.filled_slots(task, cfg.embodiment, cfg.seed, cfg.episode_role)
        out.extend((task, i) for i in range(cfg.episodes) if i not in have)
    return out


def load_recorder(spec: str) -> Callable[..., Recording]:
    """The recorder named ``"module:function"`` (signature of :func:`studio.sim.experts.record_expert`)."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


# ---------------------------------------------------------------------- worker side
_WORKER: dict = {}


def _init_worker(cfg_dict: dict) -> None:
    cfg = CollectConfig(**cfg_dict)
    recorder = load_recorder(cfg.recorder_spec)
    env = None
    if "env" in inspect.signature(recorder).parameters:
        from studio.sim.env import make_env

        env = make_env(cfg.scene, cfg.robot, image_size=cfg.frame_size)
    _WORKER.update(cfg=cfg, recorder=recorder, env=env, store=EpisodeStore(cfg.data_dir))


def _make_slot(slot: tuple[str, int]) -> tuple[str, int, bool, int, str | None]:
    """Fill one slot: (task, index, stored, failed attempts, error message or None)."""
    cfg: CollectConfig = _WORKER["cfg"]
    task, index = slot
    failures = 0
    kwargs: dict[str, Any] = {"image_size": cfg.frame_size, "min_frames": cfg.min_frames}
    if _WORKER["env"] is not None:
        kwargs["env"] = _WORKER["env"]
    try:
        for attempt in range(cfg.max_attempts):
            seed = episode_seed(cfg.seed, cfg.seed_key, task, index, attempt)
            rec = _WORKER["recorder"](cfg.scene, cfg.robot, task, seed, **kwargs)
            if not rec.success:
                failures += 1
                continue
            try:
                _WORKER["store"].add_episode(
                    rec,
                    role=cfg.episode_role,
                    embodiment=cfg.embodiment,
                    source="scripted",
                    collect_seed=cfg.seed,
                    collect_index=index,
                    extra={"attempt": attempt},
                )
            except StoreError as e:
                filled = _WORKER["store"].catalog.filled_slots(
                    task, cfg.embodiment, cfg.seed, cfg.episode_role
                )
                if index in filled:
                    return task, index, True, failures, None  # another collector filled it meanwhile
                raise e
            return task, index, True, failures, None
        return task, index, False, failures, None
    except Exception as e:
        last = traceback.format_exception_only(type(e), e)[-1].strip()
        return task, index, False, failures, f"{task} #{index}: {last}"


def _close_worker() -> None:
    if _WORKER.get("env") is not None:
        _WORKER["env"].close()
    if _WORKER.get("store") is not None:
        _WORKER["store"].close()
    _WORKER.clear()


# ---------------------------------------------------------------------- driver
def collect(
    cfg: CollectConfig,
    *,
    on_slot: Callable[[SlotDone], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> CollectResult:
    """Run (or resume) a collection; returns what was done.

    ``on_slot`` is called after every slot tried (:class:`SlotDone`). ``should_stop`` is asked before each slot;
    once it says True no further slot starts and the result says ``stopped`` (the slot being made when it turned
    True is finished and stored first: episodes are stored whole). It needs ``workers == 1``.
    """
    from tqdm import tqdm

    if should_stop is not None and cfg.workers != 1:
        raise ValueError("collect(should_stop=...) runs the slots in this process: use workers=1")

    tasks = resolve_tasks(cfg.scene, cfg.tasks)
    store = EpisodeStore(cfg.data_dir)
    report = store.check()
    if not report.ok:
        print(report.summary(), file=sys.stderr)
    todo = missing_slots(store, cfg, tasks)
    requested = len(tasks) * cfg.episodes
    made, failed_attempts = 0, 0
    missing: list[tuple[str, int]] = []
    errors: list[str] = []
    stopped = False
    start = time.perf_counter()

    def account(res: tuple[str, int, bool, int, str | None], done: int) -> None:
        nonlocal made, failed_attempts
        made, failed_attempts = _account(res, made, failed_attempts, missing, errors, bar)
        if on_slot is not None:
            on_slot(
                SlotDone(
                    task=res[0],
                    index=res[1],
                    stored=res[2],
                    done=done,
                    todo=len(todo),
                    requested=requested,
                    already_present=requested - len(todo),
                    made=made,
                    failed_attempts=failed_attempts,
                    missing=len(missing),
                )
            )

    bar = tqdm(
        total=len(todo),
        desc=f"collect {cfg.scene} {cfg.robot} ({cfg.episode_role})",
        unit="ep",
        disable=not cfg.progress,
        dynamic_ncols=True,
    )
    cfg_dict = asdict(cfg)
    cfg_dict["progress"] = False
    try:
        if cfg.workers == 1 or len(todo) <= 1:
            _init_worker(cfg_dict)
            try:
                for done, slot in enumerate(todo, 1):
                    if should_stop is not None and should_stop():
                        stopped = True
                        break
                    account(_make_slot(slot), done)
            finally:
                _close_worker()
        else:
            ctx = mp.get_context("spawn")
            with ctx.Pool(
                min(cfg.workers, len(todo)), initializer=_init_worker, initargs=(cfg_dict,)
            ) as pool:
                for done, res in enumerate(pool.imap_unordered(_make_slot, todo), 1):
                    account(res, done)
    finally:
        bar.close()
        store.close()
    return CollectResult(
        requested=requested,
        already_present=requested - len(todo),
        made=made,
        failed_attempts=failed_attempts,
        missing=sorted(missing),
        errors=errors,
        seconds=time.perf_counter() - start,
        stopped=stopped,
    )


def _account(res, made, failed_attempts, missing, errors, bar) -> tuple[int, int]:
    task, index, ok, failures, error = res
    failed_attempts += failures
    if ok:
        made += 1
    else:
        missing.append((task, index))
    if error:
        errors.append(error)
    bar.update(1)
    bar.set_postfix(failed=failed_attempts, refresh=False)
    return made, failed_attempts


# ---------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="pick_place", help="scene family (pick_place, push, metaworld)")
    parser.add_argument(
        "--robot",
        required=True,
        choices=sorted(ROLE_OF_ROBOT),
        help="sawyer = expert, hand = expert (a simulated person, embodiment 'human'), panda = agent unless "
        "--role expert (metaworld: sawyer)",
    )
    parser.add_argument(
        "--role",
        choices=ROLES,
        default=None,
        help="store the episodes as this role (default: the robot's; 'expert' makes Panda demonstrations)",
    )
    parser.add_argument(
        "--tasks",
        nargs="+",
        default=["all"],
        help="'all', 'train', 'test' (= 'held-out') or task names (space- or comma-separated), "
        "e.g. 'pick_place/cube->red'",
    )
    parser.add_argument("--episodes", type=int, default=100, help="episodes per task")
    parser.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the run")
    parser.add_argument(
        "--image-size",
        type=int,
        nargs=2,
        default=None,
        metavar=("H", "W"),
        help="frame size (default: 240 320; metaworld 224 224)",
    )
    parser.add_argument("--min-frames", type=int, default=20, help="frames stored per episode")
    parser.add_argument("--max-attempts", type=int, default=5, help="tries per slot before giving up")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    try:
        cfg = CollectConfig(
            scene=args.scene,
            robot=args.robot,
            role=args.role,
            tasks=list(args.tasks),
            episodes=args.episodes,
            workers=args.workers,
            seed=args.seed,
            image_size=tuple(args.image_size) if args.image_size else None,
            min_frames=args.min_frames,
            max_attempts=args.max_attempts,
            data_dir=args.data_dir,
            progress=not args.no_progress,
        )
        result = collect(cfg)
    except ValueError as e:
        print(f"studio collect: {e}", file=sys.stderr)
        return 2
    print(result.summary())
    for err in result.errors[:10]:
        print(f"  error: {err}", file=sys.stderr)
    return 0 if not result.missing else 1
