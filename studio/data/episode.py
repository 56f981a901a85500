"""The stored episode: its metadata, its frames, its per-step arrays and its camera, and their files.

An episode directory holds exactly three files:

* ``meta.json`` — :class:`EpisodeMeta` plus the camera model (``"camera"``) and a format version;
* ``frames.mp4`` — the external camera's frames, H.264 / yuv420p (see :mod:`studio.data.video`);
* ``arrays.npz`` — ``frame_times`` (F,) seconds of each frame, ``frame_steps`` (F,) control step of each
  frame (simulated episodes only) and the per-step arrays of :data:`studio.sim.recording.ARRAY_FIELDS`
  (absent for human videos, which have no robot state).

The files are written here; making them durable and visible atomically is the store's job
(:mod:`studio.data.store`).
"""

from __future__ import annotations

import json
import secrets
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from studio.data import video
from studio.sim.camera import CameraModel
from studio.sim.recording import ARRAY_FIELDS, EMBODIMENT_OF_ROBOT, Recording, robot_of

FORMAT_VERSION = 1

EMBODIMENTS = ("sawyer", "panda", "human")
ROLES = ("expert", "agent")
SOURCES = ("scripted", "teleop", "upload", "import", "rollout")

META_FILE = "meta.json"
FRAMES_FILE = "frames.mp4"
ARRAYS_FILE = "arrays.npz"
EPISODE_FILES = (META_FILE, FRAMES_FILE, ARRAYS_FILE)


class EpisodeError(ValueError):
    """An episode's content or metadata is invalid."""


def new_episode_id(created: float | None = None) -> str:
    """A unique, time-sortable id such as ``20250131-142501-042-9f3a1c``."""
    t = time.time() if created is None else created
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(t))
    return f"{stamp}-{int((t % 1) * 1000):03d}-{secrets.token_hex(3)}"


def scene_of_task(task: str) -> str:
    """The scene family a task belongs to: the part of its name before the first ``/``."""
    if "/" not in task or not task.split("/", 1)[0] or not task.split("/", 1)[1]:
        raise EpisodeError(f"task names look like '<scene>/<name>', got {task!r}")
    return task.split("/", 1)[0]


@dataclass(frozen=True)
class EpisodeMeta:
    """What the catalog knows about an episode.

    Attributes:
        id: unique episode id (:func:`new_episode_id`).
        task: full task name, e.g. ``"pick_place/cube->red"``.
        scene: scene family, e.g. ``"pick_place"``.
        embodiment: ``"sawyer"``, ``"panda"`` or ``"human"`` (an uploaded video, or the simulated hand's
            episodes, which have robot state like the arms').
        role: ``"expert"`` (demonstration video) or ``"agent"`` (trajectory to imitate).
        source: how it was made: ``"scripted"``, ``"teleop"``, ``"upload"``, ``"import"`` or ``"rollout"``.
        seed: the seed the scene was reset with (None for human videos).
        success: the task's success predicate at the end (None when unknown, e.g. human videos).
        created: creation time, seconds since the epoch (UTC).
        num_frames: number of stored video frames F.
        num_steps: number of control steps T of the per-step arrays (0 when there are none).
        height, width: frame size in pixels.
        fps: nominal frame rate of the video.
        control_dt: seconds between two control steps (None without arrays).
        object_names: names of the K objects in ``object_poses``.
        collect_seed, collect_index: the slot of a scripted collection run (base seed, episode index)
            this episode fills; None otherwise. Collection resumes by looking for missing slots.
        extra: free-form JSON-serialisable details (original file name of an upload, trim, ...).
    """

    id: str
    task: str
    scene: str
    embodiment: str
    role: str
    source: str
    seed: int | None
    success: bool | None
    created: float
    num_frames: int
    num_steps: int
    height: int
    width: int
    fps: float
    control_dt: float | None = None
    object_names: tuple[str, ...] = ()
    collect_seed: int | None = None
    collect_index: int | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "object_names", tuple(self.object_names))
        if self.embodiment not in EMBODIMENTS:
            raise EpisodeError(f"embodiment must be one of {EMBODIMENTS}, got {self.embodiment!r}")
        if self.role not in ROLES:
            raise EpisodeError(f"role must be one of {ROLES}, got {self.role!r}")
        if self.source not in SOURCES:
            raise EpisodeError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.embodiment == "human" and self.role != "expert":
            raise EpisodeError("a human video can only be an expert demonstration (role 'expert')")
        scene_of_task(self.task)  # raises on a malformed task name
        if not self.scene:
            raise EpisodeError("an episode needs a scene name")
        if self.num_frames < 1:
            raise EpisodeError(f"an episode needs at least one frame, got {self.num_frames}")
        if (self.collect_seed is None) != (self.collect_index is None):
            raise EpisodeError("collect_seed and collect_index are given together or not at all")

    @property
    def has_arrays(self) -> bool:
        return self.num_steps > 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["object_names"] = list(self.object_names)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeMeta:
        names = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - names
        if unknown:
            raise EpisodeError(f"unknown episode metadata fields {sorted(unknown)}")
        return cls(**d)


@dataclass
class Episode:
    """A complete episode in memory.

    Attributes:
        meta: the metadata.
        camera: the external camera the frames were taken with (size equal to the frames').
        frames: (F, H, W, 3) uint8 RGB.
        frame_times: (F,) float64, seconds since the start of the episode.
        frame_steps: (F,) int64 control step of each frame, or None when there are no per-step arrays.
        arrays: the per-step arrays of :data:`ARRAY_FIELDS` (all of them), or empty.
    """

    meta: EpisodeMeta
    camera: CameraModel
    frames: np.ndarray
    frame_times: np.ndarray
    frame_steps: np.ndarray | None = None
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        m = self.meta
        f = self.frames
        if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8:
            raise EpisodeError(f"frames must be (F, H, W, 3) uint8, got {f.shape} {f.dtype}")
        if (len(f), f.shape[1], f.shape[2]) != (m.num_frames, m.height, m.width):
            raise EpisodeError(
                f"frames {f.shape[:3]} disagree with metadata (F, H, W) = {(m.num_frames, m.height, m.width)}"
            )
        if (self.camera.height, self.camera.width) != (m.height, m.width):
            raise EpisodeError(
                f"camera size {self.camera.height}x{self.camera.width} differs from frames {m.height}x{m.width}"
            )
        if self.frame_times.shape != (m.num_frames,):
            raise EpisodeError(f"frame_times must be ({m.num_frames},), got {self.frame_times.shape}")
        if self.arrays:
            missing = set(ARRAY_FIELDS) - set(self.arrays)
            if missing:
                raise EpisodeError(f"per-step arrays lack {sorted(missing)}")
            for k, a in self.arrays.items():
                if len(a) != m.num_steps:
                    raise EpisodeError(f"array {k!r} has {len(a)} steps, metadata says {m.num_steps}")
            if self.frame_steps is None or self.frame_steps.shape != (m.num_frames,):
                raise EpisodeError("an episode with per-step arrays needs frame_steps (F,)")
            if self.frame_steps.min() < 0 or self.frame_steps.max() >= m.num_steps:
                raise EpisodeError(f"frame_steps must lie in [0, {m.num_steps}), got {self.frame_steps}")
            if m.object_names and self.arrays["object_poses"].shape[1] != len(m.object_names):
                raise EpisodeError("object_poses has a different number of objects than object_names")
        elif m.num_steps != 0:
            raise EpisodeError(f"metadata says {m.num_steps} steps but the episode has no per-step arrays")

    # ------------------------------------------------------------------ conversions
    @classmethod
    def from_recording(
        cls,
        rec: Recording,
        *,
        role: str,
        source: str,
        embodiment: str | None = None,
        episode_id: str | None = None,
        created: float | None = None,
        collect_seed: int | None = None,
        collect_index: int | None = None,
        extra: dict | None = None,
    ) -> Episode:
        """Wrap a simulator :class:`Recording` with the metadata the store adds (role, source, ...)."""
        created = time.time() if created is None else created
        steps = np.asarray(rec.frame_steps, dtype=np.int64)
        times = np.asarray(rec.arrays["time"], dtype=np.float64)[steps]
        meta = EpisodeMeta(
            id=episode_id or new_episode_id(created),
            task=rec.task,
            scene=rec.scene,
            embodiment=embodiment or EMBODIMENT_OF_ROBOT.get(rec.robot, rec.robot),
            role=role,
            source=source,
            seed=int(rec.seed),
            success=bool(rec.success),
            created=created,
            num_frames=len(rec.frames),
            num_steps=rec.num_steps,
            height=rec.frames.shape[1],
            width=rec.frames.shape[2],
            fps=nominal_fps(steps, rec.control_dt),
            control_dt=float(rec.control_dt),
            object_names=tuple(rec.object_names),
            collect_seed=collect_seed,
            collect_index=collect_index,
            extra=dict(extra or {}),
        )
        arrays = {k: np.asarray(rec.arrays[k]) for k in ARRAY_FIELDS}
        return cls(meta, rec.camera, np.ascontiguousarray(rec.frames), times, steps, arrays)

    def to_recording(self) -> Recording:
        """The simulator's view of this episode (only for episodes with per-step arrays)."""
        if not self.arrays:
            raise EpisodeError(
                f"episode {self.meta.id} has no per-step arrays (embodiment {self.meta.embodiment})"
            )
        frame_steps, control_dt = self.frame_steps, self.meta.control_dt
        if frame_steps is None or control_dt is None:  # __post_init__ already requires frame_steps
            raise EpisodeError(f"episode {self.meta.id} has per-step arrays but no frame_steps or control_dt")
        return Recording(
            scene=self.meta.scene,
            robot=robot_of(self.meta.embodiment),
            task=self.meta.task,
            seed=int(self.meta.seed if self.meta.seed is not None else 0),
            success=bool(self.meta.success),
            camera=self.camera,
            frames=self.frames,
            frame_steps=frame_steps,
            arrays=dict(self.arrays),
            object_names=list(self.meta.object_names),
            control_dt=float(control_dt),
        )

    def with_meta(self, **changes) -> Episode:
        return replace(self, meta=replace(self.meta, **changes))


def nominal_fps(frame_steps: np.ndarray, control_dt: float) -> float:
    """Frame rate of frames rendered every few control steps (median spacing); 1/control_dt for one frame."""
    if len(frame_steps) < 2:
        return 1.0 / control_dt
    spacing = float(np.median(np.diff(frame_steps)))
    return 1.0 / (control_dt * max(spacing, 1.0))


# ---------------------------------------------------------------------- files
def write_episode_files(ep: Episode, directory: Path, crf: int = 18) -> list[Path]:
    """Write the three files of ``ep`` into an existing, empty ``directory``; returns their paths."""
    directory = Path(directory)
    video_path = directory / FRAMES_FILE
    video.write_video(video_path, ep.frames, fps=ep.meta.fps, crf=crf)
    # Any: numpy's stub of savez declares allow_pickle: bool beside **kwds, so unpacking a dict of arrays
    # into it does not type-check.
    arrays: dict[str, Any] = {"frame_times": np.asarray(ep.frame_times, dtype=np.float64)}
    if ep.frame_steps is not None:
        arrays["frame_steps"] = np.asarray(ep.frame_steps, dtype=np.int64)
    arrays.update({k: np.asarray(v) for k, v in ep.arrays.items()})
    arrays_path = directory / ARRAYS_FILE
    with open(arrays_path, "wb") as fh:
        np.savez(fh, **arrays)
    meta_path = directory / META_FILE
    doc = {"format_version": FORMAT_VERSION, **ep.meta.to_dict(), "camera": ep.camera.to_dict()}
    meta_path.write_text(json.dumps(doc, indent=1, sort_keys=True))
    return [video_path, arrays_path, meta_path]


def read_meta(directory: Path) -> tuple[EpisodeMeta, CameraModel]:
    """The metadata and camera of the episode stored in ``directory``."""
    doc = json.loads((Path(directory) / META_FILE).read_text())
    version = doc.pop("format_version", None)
    if version != FORMAT_VERSION:
        raise EpisodeError(f"{directory}: unsupported episode format version {version!r}")
    camera = CameraModel.from_dict(doc.pop("camera"))
    return EpisodeMeta.from_dict(doc), camera


def read_arrays(directory: Path) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """(frame_times, frame_steps or None, per-step arrays) of the episode stored in ``directory``."""
    with np.load(Path(directory) / ARRAYS_FILE, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    times = data.pop("frame_times")
    steps = data.pop("frame_steps", None)
    return times, steps, data


def read_episode(directory: Path) -> Episode:
    """Load a whole stored episode (decodes the video)."""
    meta, camera = read_meta(directory)
    times, steps, arrays = read_arrays(directory)
    frames = video.read_video(Path(directory) / FRAMES_FILE, size=(meta.height, meta.width)).frames
    if len(frames) != meta.num_frames:
        raise EpisodeError(f"{directory}: video has {len(frames)} frames, metadata says {meta.num_frames}")
    return Episode(meta, camera, frames, times, steps, arrays)
