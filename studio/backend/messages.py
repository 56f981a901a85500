"""Every message on the studio's Zenoh bus: typed, frozen, versioned records and their binary encoding.

This module is the single source of truth for the wire protocol; ``docs/protocol.md`` embeds the tables
that :mod:`studio.backend.protocol_doc` generates from the classes below (a test keeps the two in sync).

Wire format: one byte :data:`PROTOCOL_VERSION`, then MessagePack of the message as an array whose first
element is the message's tag (its class name) followed by its fields in declaration order. Fields may only
ever be *appended* (with a default) within a version: an older peer ignores trailing fields it does not
know, a newer peer fills in defaults for fields an older one did not send. Any other change bumps the
version. Poses travel as packed little-endian float32 arrays, images as JPEG or raw RGB bytes with their
shape, so a 60 Hz pose stream of a whole scene costs about 1.5 kB per update.

:func:`decode` validates everything it returns (types, ranges, identifiers, finite numbers, byte lengths
against shapes) and raises nothing but :class:`ProtocolError` on malformed, unknown or out-of-range input.
"""

from __future__ import annotations

import math
import sys
import typing
from typing import Annotated, Any, Literal, Union

import msgspec
import numpy as np

#: Bumped on every incompatible change of any message below.
PROTOCOL_VERSION = 1

_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"

#: Identifier of a worker, session, job or transfer; safe as one key-expression chunk.
Id = Annotated[str, msgspec.Meta(pattern=_ID_PATTERN)]
#: A scene, robot, task, camera or artifact name (task names contain '/' and '->').
Name = Annotated[str, msgspec.Meta(min_length=1, max_length=200)]
#: Free text for humans (reasons, activity, progress messages).
Text = Annotated[str, msgspec.Meta(max_length=4096)]
Count = Annotated[int, msgspec.Meta(ge=0)]
Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]
Seed = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]
Pixels = Annotated[int, msgspec.Meta(ge=1, le=4096)]
Quality = Annotated[int, msgspec.Meta(ge=1, le=100)]
Role = Literal["expert", "agent"]
#: A teleop session's owner token (unguessable; see :class:`SessionInfo`).
OwnerToken = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_\-]{16,128}$")]
ImageEncoding = Literal["jpeg", "raw"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
TERMINAL_JOB_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})

#: Largest step of :attr:`EeTarget.seq` from the last applied command (about 45 minutes of commands at 60 Hz).
MAX_SEQ_STEP = 1 << 18

#: Float32 numbers per body in :class:`PoseFrame` (position xyz, quaternion wxyz).
POSE_WIDTH = 7


class ProtocolError(ValueError):
    """A payload is not a valid message of this protocol version (or not the message expected)."""


def _require_finite(owner: str, **values: float | tuple[float, ...] | None) -> None:
    for name, value in values.items():
        if value is None:
            continue
        items = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) for v in items):
            raise ValueError(f"{owner}.{name} must be finite, got {value!r}")


class Message(msgspec.Struct, frozen=True, tag=True, array_like=True):
    """Base of every bus message; the tag is the class name.

    Subclasses repeat ``frozen=True``: msgspec inherits it, but type checkers only see it when it is spelled out.
    """


# ---------------------------------------------------------------------------------------------- common
class ErrorReply(Message, frozen=True):
    """Answer to a query that could not be served. ``code`` is machine-readable, ``message`` for humans."""

    code: Literal["bad_request", "not_found", "busy", "unavailable", "conflict", "internal"]
    message: Text


class Ack(Message, frozen=True):
    """Plain acknowledgement of a request that returns nothing else."""

    message: Text = ""


# ---------------------------------------------------------------------------------------------- presence
class WorkerStatus(Message, frozen=True):
    """What a worker is and does; published on ``studio/workers/<kind>/<id>/status`` on every change."""

    worker: Id
    kind: Id
    host: Name
    pid: Count
    state: Literal["idle", "busy", "stopping"]
    activity: Text
    job_kinds: tuple[Id, ...]
    unavailable: dict[str, Text]
    job: Id | None
    sessions: Count
    started_at: float
    updated_at: float

    def __post_init__(self) -> None:
        _require_finite("WorkerStatus", started_at=self.started_at, updated_at=self.updated_at)


# ---------------------------------------------------------------------------------------------- teleop requests
class ForkStart(msgspec.Struct, frozen=True, array_like=True):
    """A recorded episode a teleop session continues instead of starting fresh (see :class:`OpenSession`).

    ``states`` (T, S) float64 are the episode's MuJoCo integration states from its reset to the tick it
    continues from, ``arrays`` its recorded per-tick arrays over the same T ticks; the session restores the
    last state exactly and records on from there, the T ticks included. ``gripper`` is the gripper command
    in force at that tick, ``control_dt`` the episode's control period (the session steps at it, so the
    recording keeps one rate). ``origin`` is stored with the saved episode as ``forked_from`` (e.g. the
    rollout and step it was forked at).
    """

    draft: Id
    states: ArrayData
    arrays: dict[str, ArrayData]
    gripper: Unit
    control_dt: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]
    role: Role
    origin: dict[str, Any] = {}

    def __post_init__(self) -> None:
        if self.states.dtype != "float64" or len(self.states.shape) != 2 or self.states.shape[0] < 1:
            raise ValueError(
                f"ForkStart.states must be (T, S) float64 with T >= 1, got {self.states.dtype}"
                f"{list(self.states.shape)}"
            )
        for name, a in self.arrays.items():
            if not a.shape or a.shape[0] != self.states.shape[0]:
                raise ValueError(
                    f"ForkStart.arrays[{name!r}] has {a.shape[:1]} ticks, states have {self.states.shape[0]}"
                )


class OpenSession(Message, frozen=True):
    """Create (or re-create) the teleop session named by the key: a fresh scene reset to (task, seed), or,
    with ``fork``, that episode restored at its last recorded tick and recording on from there."""

    scene: Name
    robot: Name
    task: Name
    seed: Seed
    image_height: Pixels = 240
    image_width: Pixels = 320
    fork: ForkStart | None = None


class ResetSession(Message, frozen=True):
    """Reset the session's scene; None keeps the current task or seed. Discards an unsaved recording."""

    task: Name | None = None
    seed: Seed | None = None


class StartRecording(Message, frozen=True):
    """Start recording; by default the scene is reset first so the episode starts at its seed's state.

    ``role`` defaults to ``expert`` for the Sawyer and ``agent`` for the Panda.
    """

    role: Role | None = None
    reset: bool = True
    #: Journal the recording's ticks as :class:`DraftChunk` messages under this id, so a worker that dies
    #: mid-recording loses nothing the client has received.
    draft: Id | None = None


class StopRecording(Message, frozen=True):
    """Stop recording and store the episode; the outcome arrives later as :class:`EpisodeSaved`.

    ``success`` is the user's verdict (the UI pre-fills it with the task's predicate); None stores the
    predicate's value at the moment recording stops.
    """

    success: bool | None = None


class DiscardRecording(Message, frozen=True):
    """Stop recording and drop what was recorded."""


class RequestFrame(Message, frozen=True):
    """Render one camera image now; answered with an :class:`ImageFrame` (also published on ``frames``)."""

    camera: Name = "external"
    encoding: ImageEncoding = "jpeg"
    quality: Quality = 80


class StreamFrames(Message, frozen=True):
    """Publish camera images on ``frames`` at up to ``hz`` (0 stops). Rendering never delays physics."""

    camera: Name = "external"
    hz: Annotated[float, msgspec.Meta(ge=0.0, le=30.0)] = 10.0
    encoding: ImageEncoding = "jpeg"
    quality: Quality = 80


class GetGeometry(Message, frozen=True):
    """Ask for the scene's visual geometry (answered with :class:`SceneGeometry`)."""


class CloseSession(Message, frozen=True):
    """End the session and free its simulator."""


# ---------------------------------------------------------------------------------------------- teleop replies and streams
class SessionInfo(Message, frozen=True):
    """Answer to :class:`OpenSession` / :class:`ResetSession`: what the session simulates.

    ``body_names[i]`` names row ``i`` of every :class:`PoseFrame`; ``camera`` is
    :meth:`studio.sim.camera.CameraModel.to_dict` of the external camera.
    """

    session: Id
    worker: Id
    scene: Name
    robot: Name
    task: Name
    seed: Seed
    control_dt: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]
    body_names: tuple[str, ...]
    cameras: tuple[str, ...]
    camera: dict[str, Any]
    image_height: Pixels
    image_width: Pixels
    #: The session's owner token, in the answer to the :class:`OpenSession` that created it (and to its owner's
    #: later requests): every later request and :class:`EeTarget` must carry it as its Zenoh attachment.
    owner: OwnerToken | None = None


class SessionState(Message, frozen=True):
    """A session's recording state; reply to recording requests and published on ``status``."""

    session: Id
    state: Literal["idle", "recording", "closed"]
    task: Name
    seed: Seed
    step: Count
    recorded_steps: Count
    saving: Count
    success: bool
    message: Text = ""


class EpisodeSaved(Message, frozen=True):
    """A recorded episode is durable in the store (published on the session's ``status``)."""

    session: Id
    episode: Name
    task: Name
    role: Role
    steps: Count
    frames: Count
    success: bool
    via: Literal["data-dir", "bus"]
    draft: Id | None = None


class EpisodeNotSaved(Message, frozen=True):
    """A recorded episode could not reach the store yet; ``kept_at`` says where it waits (never lost)."""

    session: Id
    reason: Text
    kept_at: Text
    draft: Id | None = None


class EeTarget(Message, frozen=True):
    """Teleop command on ``cmd``: end-effector (grasp point) target in the world and gripper closure.

    Latest wins: the worker applies only the newest target at each control tick; ``seq`` increases, by at most
    :data:`MAX_SEQ_STEP` from one applied command to the next (a command further ahead is dropped). It carries
    the session's owner token as its attachment.
    """

    seq: Count
    pos: Vec3
    gripper: Unit

    def __post_init__(self) -> None:
        _require_finite("EeTarget", pos=self.pos)


class PoseFrame(Message, frozen=True):
    """Body poses after one control tick (``poses``: ``body_count`` × 7 float32, xyz + quaternion wxyz).

    ``ack_seq`` is the ``seq`` of the newest :class:`EeTarget` applied before this tick (-1: none yet).
    """

    seq: Count
    step: Count
    sim_time: float
    ack_seq: Annotated[int, msgspec.Meta(ge=-1)]
    body_count: Count
    poses: bytes
    ee_pos: Vec3
    gripper: Unit

    def __post_init__(self) -> None:
        _require_finite("PoseFrame", sim_time=self.sim_time, ee_pos=self.ee_pos)
        expected = self.body_count * POSE_WIDTH * 4
        if len(self.poses) != expected:
            raise ValueError(
                f"PoseFrame.poses has {len(self.poses)} bytes, expected {expected} for {self.body_count} bodies"
            )

    @classmethod
    def pack(cls, poses: np.ndarray, **fields: Any) -> PoseFrame:
        """Build a frame from a (B, 7) array of positions and quaternions."""
        arr = np.ascontiguousarray(poses, dtype="<f4")
        if arr.ndim != 2 or arr.shape[1] != POSE_WIDTH:
            raise ValueError(f"PoseFrame.pack needs a (B, {POSE_WIDTH}) array, got shape {arr.shape}")
        return cls(body_count=arr.shape[0], poses=arr.tobytes(), **fields)

    def poses_array(self) -> np.ndarray:
        """The poses as a (B, 7) float32 array."""
        return np.frombuffer(self.poses, dtype="<f4").reshape(self.body_count, POSE_WIDTH)


class ImageFrame(Message, frozen=True):
    """One RGB camera image: JPEG bytes, or raw row-major (height, width, 3) uint8 bytes."""

    camera: Name
    step: Count
    height: Pixels
    width: Pixels
    encoding: ImageEncoding
    data: bytes

    def __post_init__(self) -> None:
        if self.encoding == "raw" and len(self.data) != self.height * self.width * 3:
            raise ValueError(
                f"ImageFrame raw data has {len(self.data)} bytes, expected {self.height}x{self.width}x3"
            )
        if self.encoding == "jpeg" and not self.data.startswith(b"\xff\xd8"):
            raise ValueError("ImageFrame jpeg data does not start with a JPEG marker")

    @classmethod
    def from_array(
        cls, image: np.ndarray, *, camera: str, step: int, encoding: ImageEncoding = "jpeg", quality: int = 80
    ) -> ImageFrame:
        img = np.ascontiguousarray(image, dtype=np.uint8)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"ImageFrame.from_array needs an (H, W, 3) image, got shape {img.shape}")
        if encoding == "raw":
            data = img.tobytes()
        elif encoding == "jpeg":
            import cv2

            ok, buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
            if not ok:
                raise ValueError("JPEG encoding failed")
            data = buf.tobytes()
        else:
            raise ValueError(f"unknown image encoding {encoding!r}; use 'jpeg' or 'raw'")
        return cls(
            camera=camera, step=step, height=img.shape[0], width=img.shape[1], encoding=encoding, data=data
        )

    def to_array(self) -> np.ndarray:
        """The image as (height, width, 3) uint8 RGB; raises :class:`ProtocolError` on corrupt JPEG data."""
        if self.encoding == "raw":
            return np.frombuffer(self.data, dtype=np.uint8).reshape(self.height, self.width, 3)
        import cv2

        bgr = cv2.imdecode(np.frombuffer(self.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[:2] != (self.height, self.width):
            raise ProtocolError(f"ImageFrame: corrupt JPEG or size differs from {self.height}x{self.width}")
        return np.ascontiguousarray(bgr[:, :, ::-1])


class GeomSpec(msgspec.Struct, frozen=True, array_like=True):
    """One visual geom, attached to ``body`` (an index into ``SceneGeometry.body_names``).

    ``size`` follows MuJoCo's geom_size for the type; ``mesh`` indexes ``SceneGeometry.meshes`` (-1: none).
    ``group`` is MuJoCo's geom group (the studio's cameras hide groups ≥ 3, collision-only geoms).
    """

    body: Count
    type: Literal["plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh", "sdf"]
    group: int
    size: Vec3
    pos: Vec3
    quat: Vec4
    rgba: Vec4
    mesh: Annotated[int, msgspec.Meta(ge=-1)]


class MeshSpec(msgspec.Struct, frozen=True, array_like=True):
    """Triangle mesh in its body-local mesh frame: float32 vertices (V, 3) and int32 faces (F, 3)."""

    name: str
    vertices: bytes
    faces: bytes

    def __post_init__(self) -> None:
        if len(self.vertices) % 12 or len(self.faces) % 12:
            raise ValueError("MeshSpec vertices and faces must be whole (n, 3) float32 / int32 arrays")


class SceneGeometry(Message, frozen=True):
    """Everything a viewer needs to draw the scene; bodies move with :class:`PoseFrame`."""

    body_names: tuple[str, ...]
    geoms: tuple[GeomSpec, ...]
    meshes: tuple[MeshSpec, ...]

    def __post_init__(self) -> None:
        for g in self.geoms:
            if g.body >= len(self.body_names) or g.mesh >= len(self.meshes):
                raise ValueError("SceneGeometry: a geom refers to a body or mesh that does not exist")


# ---------------------------------------------------------------------------------------------- jobs
class JobSubmit(Message, frozen=True):
    """Put a job in the queue. ``spec`` is the handler's input (its own schema, validated by the handler).

    A job whose worker is lost is re-queued (up to ``max_attempts`` attempts in all) when
    ``requeue_on_worker_loss``, else it fails with the reason.
    """

    job: Id
    kind: Id
    worker_kind: Id
    spec: dict[str, Any]
    requeue_on_worker_loss: bool = False
    max_attempts: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3


class JobCancel(Message, frozen=True):
    """Cancel a queued or running job (sent to the queue, which forwards it to the worker)."""

    job: Id
    reason: Text = ""


class JobAssign(Message, frozen=True):
    """The queue hands one attempt of a job to a worker (answered with the running :class:`JobStatus`)."""

    job: Id
    kind: Id
    attempt: Annotated[int, msgspec.Meta(ge=1)]
    spec: dict[str, Any]
    submitted_at: float
    requeue_on_worker_loss: bool = False
    max_attempts: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3


class JobStatus(Message, frozen=True):
    """A job's state. Of two statuses of one job, the one with the larger :func:`status_rank` is newer."""

    job: Id
    kind: Id
    worker_kind: Id
    state: JobState
    attempt: Annotated[int, msgspec.Meta(ge=1)]
    worker: Id | None
    reason: Text
    submitted_at: float
    updated_at: float
    queue_position: Count | None = None
    spec: dict[str, Any] = {}
    requeue_on_worker_loss: bool = False
    max_attempts: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3
    #: The worker published the attempt's JobResult before this status: the queue waits for the result before it
    #: says the job ended, so that whoever sees the end can read the result.
    has_result: bool = False

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL_JOB_STATES


class JobProgress(Message, frozen=True):
    """Progress of a running attempt: step of total, named metrics (losses, lr, samples/s...), ETA."""

    job: Id
    attempt: Annotated[int, msgspec.Meta(ge=1)]
    step: Count
    total: Count | None
    metrics: dict[str, float]
    message: Text = ""
    eta_s: float | None = None


class JobArtifact(Message, frozen=True):
    """A file a job wrote (e.g. a checkpoint), announced as soon as it is complete."""

    job: Id
    attempt: Annotated[int, msgspec.Meta(ge=1)]
    name: Name
    path: Text
    step: Count | None = None


class JobResult(Message, frozen=True):
    """What a finished job returned (handler-defined, JSON-like)."""

    job: Id
    attempt: Annotated[int, msgspec.Meta(ge=1)]
    result: dict[str, Any]


# ---------------------------------------------------------------------------------------------- episode shipping
class ArrayData(msgspec.Struct, frozen=True, array_like=True):
    """A numpy array as dtype, shape and little-endian bytes."""

    dtype: Literal["uint8", "int32", "int64", "float32", "float64"]
    shape: tuple[Count, ...]
    data: bytes

    def __post_init__(self) -> None:
        n = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != n:
            raise ValueError(
                f"ArrayData {self.dtype}{list(self.shape)} needs {n} bytes, got {len(self.data)}"
            )

    @classmethod
    def of(cls, array: np.ndarray) -> ArrayData:
        arr = np.asarray(array)
        dtype = np.dtype(arr.dtype).newbyteorder("<")
        return cls(
            dtype=dtype.name, shape=tuple(arr.shape), data=np.ascontiguousarray(arr, dtype=dtype).tobytes()
        )

    def to_array(self) -> np.ndarray:
        return (
            np.frombuffer(self.data, dtype=np.dtype(self.dtype).newbyteorder("<")).reshape(self.shape).copy()
        )


class DraftChunk(Message, frozen=True):
    """Ticks ``first_step`` … of a recording journaled under ``draft`` (on the session's ``draft`` key).

    ``states`` (n, S) float64 MuJoCo integration states and ``arrays`` the recorded per-tick arrays of the
    same n ticks. Chunks of one draft arrive in order and without gaps; a recording's last chunk is sent
    before it is stored, so the draft then holds all of it.
    """

    session: Id
    draft: Id
    first_step: Count
    states: ArrayData
    arrays: dict[str, ArrayData]

    def __post_init__(self) -> None:
        if self.states.dtype != "float64" or len(self.states.shape) != 2 or self.states.shape[0] < 1:
            raise ValueError(
                f"DraftChunk.states must be (n, S) float64 with n >= 1, got {self.states.dtype}"
                f"{list(self.states.shape)}"
            )
        for name, a in self.arrays.items():
            if not a.shape or a.shape[0] != self.states.shape[0]:
                raise ValueError(
                    f"DraftChunk.arrays[{name!r}] has {a.shape[:1]} ticks, states have {self.states.shape[0]}"
                )


class RecordingPayload(Message, frozen=True):
    """A :class:`studio.sim.recording.Recording` as shipped in :class:`EpisodeChunk` pieces."""

    scene: Name
    robot: Name
    task: Name
    seed: Seed
    success: bool
    camera: dict[str, Any]
    control_dt: float
    object_names: tuple[str, ...]
    frames: ArrayData
    frame_steps: ArrayData
    arrays: dict[str, ArrayData]


class EpisodeChunk(Message, frozen=True):
    """Piece ``index`` of ``count`` of an encoded :class:`RecordingPayload` on its way to the store host."""

    transfer: Id
    index: Count
    count: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)]
    data: bytes

    def __post_init__(self) -> None:
        if self.index >= self.count:
            raise ValueError(f"EpisodeChunk.index {self.index} is not below count {self.count}")


class EpisodeCommit(Message, frozen=True):
    """All chunks sent: verify the SHA-256 of their concatenation and store the episode."""

    transfer: Id
    count: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)]
    sha256: Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{64}$")]
    role: Role
    source: Literal["scripted", "teleop", "rollout"]
    embodiment: Name | None = None
    extra: dict[str, Any] = {}


class ChunkAck(Message, frozen=True):
    """The store host holds chunk ``index`` of ``transfer``."""

    transfer: Id
    index: Count


class EpisodeStored(Message, frozen=True):
    """Answer to :class:`EpisodeCommit`: the episode's id in the store."""

    transfer: Id
    episode: Name


# ---------------------------------------------------------------------------------------------- artifacts
#: A file's content id: the hex SHA-256 of its bytes.
ContentId = Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{64}$")]
#: A path relative to a data directory ('/'-separated, no '..', no leading '/').
DataPath = Annotated[
    str, msgspec.Meta(pattern=r"^(?!.*(^|/)\.\.?(/|$))[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$", max_length=1024)
]


class BlobGet(Message, frozen=True):
    """Ask a holder of content ``blob`` for its piece ``index``."""

    blob: ContentId
    index: Count


class BlobPart(Message, frozen=True):
    """Piece ``index`` of ``count`` of content ``blob`` (``size`` bytes in all); ``digest`` is the piece's SHA-256."""

    blob: ContentId
    index: Count
    count: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)]
    size: Count
    digest: ContentId
    data: bytes

    def __post_init__(self) -> None:
        if self.index >= self.count:
            raise ValueError(f"BlobPart.index {self.index} is not below count {self.count}")


class BlobOffer(Message, frozen=True):
    """To the store host: fetch content ``blob`` (``size`` bytes) from ``holder`` and keep it at ``path`` in the
    data directory (a job's output: a checkpoint, a plan, a run's metrics)."""

    holder: Id
    blob: ContentId
    size: Count
    path: DataPath


class EpisodeOffer(Message, frozen=True):
    """To the store host: fetch the files of stored episode ``episode`` (file name -> content id, sizes in
    ``sizes``) from ``holder`` and add them to the store as they are; ``rollout`` is the catalog row of the
    rollout it records (its ``path`` relative to the data directory), if any."""

    holder: Id
    episode: Id
    files: dict[Name, ContentId]
    sizes: dict[Name, Count]
    rollout: dict[str, Any] | None = None


class DescribeInputs(Message, frozen=True):
    """To the store host: the content id of what a ``kind`` job with ``spec`` reads, served from now on (see
    :class:`studio.backend.artifact_transfer.InputManifest`)."""

    kind: Id
    spec: dict[str, Any]


class InputsDescribed(Message, frozen=True):
    """Answer to :class:`DescribeInputs`; ``inputs`` is None for a job that reads nothing of the data directory."""

    inputs: ContentId | None


class BlobStored(Message, frozen=True):
    """Answer to :class:`BlobOffer` and :class:`EpisodeOffer`: the content is in the store host's data directory."""

    blob: ContentId
    path: DataPath


# ---------------------------------------------------------------------------------------------- codec
#: Every message class, in documentation order.
MESSAGE_TYPES: tuple[type[Message], ...] = tuple(
    cls
    for cls in vars(sys.modules[__name__]).values()
    if isinstance(cls, type) and issubclass(cls, Message) and cls is not Message
)
AnyMessage = Union[MESSAGE_TYPES]  # type: ignore[valid-type]  # noqa: UP007

_ENCODER = msgspec.msgpack.Encoder()
_DECODER = msgspec.msgpack.Decoder(AnyMessage)
_VERSION_BYTE = bytes([PROTOCOL_VERSION])


def encode(message: Message) -> bytes:
    """The wire bytes of ``message``."""
    if not isinstance(message, Message):
        raise TypeError(f"encode() takes a bus message, got {type(message).__name__}")
    return _VERSION_BYTE + _ENCODER.encode(message)


_M = typing.TypeVar("_M", bound=Message)


@typing.overload
def decode(data: bytes | bytearray | memoryview) -> Message: ...
@typing.overload
def decode(data: bytes | bytearray | memoryview, expect: type[_M]) -> _M: ...
@typing.overload
def decode(data: bytes | bytearray | memoryview, expect: tuple[type[Message], ...]) -> Message: ...


def decode(data, expect=None):
    """Parse and validate wire bytes; raises only :class:`ProtocolError`.

    ``expect`` (a class or tuple of classes) additionally requires the message to be of that type.
    """
    try:
        raw = bytes(data)
    except Exception as e:
        raise ProtocolError(f"payload is not bytes: {type(data).__name__}") from e
    if not raw:
        raise ProtocolError("empty payload")
    if raw[0] != PROTOCOL_VERSION:
        raise ProtocolError(
            f"protocol version {raw[0]} is not supported (this build speaks {PROTOCOL_VERSION})"
        )
    try:
        message = _DECODER.decode(memoryview(raw)[1:])
    except msgspec.MsgspecError as e:
        raise ProtocolError(f"invalid message: {e}") from None
    except (RecursionError, ValueError, TypeError, OverflowError) as e:
        raise ProtocolError(f"invalid message: {type(e).__name__}: {e}") from None
    if expect is not None and not isinstance(message, expect):
        names = " or ".join(t.__name__ for t in (expect if isinstance(expect, tuple) else (expect,)))
        raise ProtocolError(f"expected {names}, got {type(message).__name__}")
    return message


def status_rank(status: JobStatus) -> tuple[int, int]:
    """Order of a job's statuses: later attempts first, then queued < running < finished."""
    phase = 2 if status.terminal else (1 if status.state == "running" else 0)
    return (status.attempt, phase)
