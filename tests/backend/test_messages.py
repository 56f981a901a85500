"""The wire protocol: every message round-trips, validation rejects bad values, and no input makes a decoder
raise anything but ProtocolError (property-based fuzzing of every message type)."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from studio.backend import messages as msg

ROOT = Path(__file__).resolve().parents[2]

_ONE = msg.PoseFrame.pack(
    np.arange(14, dtype=np.float32).reshape(2, 7),
    seq=3,
    step=4,
    sim_time=0.5,
    ack_seq=2,
    ee_pos=(0.1, 0.2, 0.3),
    gripper=0.5,
)
_IMG = np.random.default_rng(0).integers(0, 255, (12, 16, 3), dtype=np.uint8)
_STATUS = msg.JobStatus(
    job="j1",
    kind="train",
    worker_kind="train",
    state="running",
    attempt=2,
    worker="t1",
    reason="",
    submitted_at=1.0,
    updated_at=2.0,
    spec={"run_dir": "/tmp/x", "steps": 3},
)

#: One valid instance of every message type.
EXAMPLES: list[msg.Message] = [
    msg.ErrorReply(code="busy", message="worker runs job j1"),
    msg.Ack(message="ok"),
    msg.WorkerStatus(
        worker="sim-a",
        kind="sim",
        host="box",
        pid=12,
        state="idle",
        activity="idle",
        job_kinds=("rollout",),
        unavailable={"train": "no torch"},
        job=None,
        sessions=1,
        started_at=1.0,
        updated_at=2.0,
    ),
    msg.OpenSession(scene="pick_place", robot="panda", task="pick_place/cube->red", seed=3),
    msg.ResetSession(task=None, seed=5),
    msg.StartRecording(role="expert", reset=False),
    msg.StopRecording(),
    msg.DiscardRecording(),
    msg.RequestFrame(camera="wrist", encoding="raw", quality=50),
    msg.StreamFrames(hz=5.0),
    msg.GetGeometry(),
    msg.CloseSession(),
    msg.SessionInfo(
        session="s1",
        worker="sim-a",
        scene="pick_place",
        robot="panda",
        task="pick_place/cube->red",
        seed=0,
        control_dt=0.016,
        body_names=("world", "base"),
        cameras=("external",),
        camera={"width": 320, "height": 240, "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        image_height=240,
        image_width=320,
    ),
    msg.SessionState(
        session="s1",
        state="recording",
        task="pick_place/cube->red",
        seed=0,
        step=10,
        recorded_steps=9,
        saving=0,
        success=False,
    ),
    msg.EpisodeSaved(
        session="s1",
        episode="20250101-000000-000-abcdef",
        task="pick_place/cube->red",
        role="agent",
        steps=40,
        frames=20,
        success=True,
        via="bus",
    ),
    msg.EpisodeNotSaved(session="s1", reason="hub unreachable", kept_at="/spool/x.payload"),
    msg.EeTarget(seq=7, pos=(0.0, 0.4, 0.2), gripper=1.0),
    _ONE,
    msg.ImageFrame.from_array(_IMG, camera="external", step=1, encoding="jpeg"),
    msg.ImageFrame.from_array(_IMG, camera="external", step=1, encoding="raw"),
    msg.SceneGeometry(
        body_names=("world", "box"),
        geoms=(
            msg.GeomSpec(
                body=1,
                type="mesh",
                group=0,
                size=(0.1, 0.1, 0.1),
                pos=(0, 0, 0),
                quat=(1, 0, 0, 0),
                rgba=(1, 0, 0, 1),
                mesh=0,
            ),
        ),
        meshes=(
            msg.MeshSpec(
                name="m",
                vertices=np.zeros((3, 3), "<f4").tobytes(),
                faces=np.array([[0, 1, 2]], "<i4").tobytes(),
            ),
        ),
    ),
    msg.JobSubmit(
        job="j1",
        kind="train",
        worker_kind="train",
        spec={"steps": 3, "nested": {"a": [1, 2.5, None]}},
        requeue_on_worker_loss=True,
    ),
    msg.JobCancel(job="j1", reason="stop"),
    msg.JobAssign(job="j1", kind="train", attempt=1, spec={}, submitted_at=1.0),
    _STATUS,
    msg.JobProgress(job="j1", attempt=1, step=5, total=10, metrics={"loss": 0.5, "lr": 1e-4}, eta_s=3.0),
    msg.JobArtifact(job="j1", attempt=1, name="checkpoint", path="/runs/x/last.pt", step=5),
    msg.JobResult(job="j1", attempt=1, result={"success": True}),
    msg.RecordingPayload(
        scene="pick_place",
        robot="panda",
        task="pick_place/cube->red",
        seed=1,
        success=False,
        camera={},
        control_dt=0.02,
        object_names=("cube",),
        frames=msg.ArrayData.of(np.zeros((1, 2, 2, 3), np.uint8)),
        frame_steps=msg.ArrayData.of(np.zeros(1, np.int64)),
        arrays={"time": msg.ArrayData.of(np.zeros(3))},
    ),
    msg.EpisodeChunk(transfer="t1", index=0, count=2, data=b"abc"),
    msg.EpisodeCommit(transfer="t1", count=2, sha256="0" * 64, role="agent", source="teleop"),
    msg.ChunkAck(transfer="t1", index=1),
    msg.EpisodeStored(transfer="t1", episode="e1"),
    msg.BlobGet(blob="a" * 64, index=2),
    msg.BlobPart(blob="a" * 64, index=0, count=1, size=3, digest="b" * 64, data=b"abc"),
    msg.BlobOffer(holder="sim-1", blob="a" * 64, size=3, path="plans/j1.npz"),
    msg.EpisodeOffer(
        holder="sim-1",
        episode="e1",
        files={"meta.json": "a" * 64},
        sizes={"meta.json": 3},
        rollout={"id": "r-1", "task": "pick_place/bar->blue", "success": True},
    ),
    msg.BlobStored(blob="a" * 64, path="episodes/e1"),
    msg.DescribeInputs(kind="plan", spec={"checkpoint": "runs/r/best.pt", "seed": 1}),
    msg.InputsDescribed(inputs=None),
    msg.OpenSession(
        scene="pick_place",
        robot="panda",
        task="pick_place/bar->blue",
        seed=5,
        fork=msg.ForkStart(
            draft="d-1",
            states=msg.ArrayData.of(np.arange(6.0).reshape(2, 3)),
            arrays={"time": msg.ArrayData.of(np.array([0.0, 0.02]))},
            gripper=1.0,
            control_dt=0.02,
            role="agent",
            origin={"rollout": "r-1", "step": 1},
        ),
    ),
    msg.StartRecording(role="expert", reset=True, draft="d-2"),
    msg.DraftChunk(
        session="s1",
        draft="d-2",
        first_step=4,
        states=msg.ArrayData.of(np.zeros((3, 5))),
        arrays={"time": msg.ArrayData.of(np.array([0.04, 0.05, 0.06]))},
    ),
]
ENCODED = [msg.encode(m) for m in EXAMPLES]


def test_examples_cover_every_message_type():
    assert {type(m) for m in EXAMPLES} == set(msg.MESSAGE_TYPES)


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(message):
    data = msg.encode(message)
    assert data[0] == msg.PROTOCOL_VERSION
    back = msg.decode(data)
    assert back == message and type(back) is type(message)
    assert msg.decode(data, type(message)) == message


def test_poses_and_images_are_compact_and_exact():
    assert _ONE.poses_array().tolist() == np.arange(14, dtype=np.float32).reshape(2, 7).tolist()
    assert len(_ONE.poses) == 2 * 7 * 4
    raw = msg.decode(msg.encode(msg.ImageFrame.from_array(_IMG, camera="c", step=0, encoding="raw")))
    assert np.array_equal(raw.to_array(), _IMG)
    jpeg = msg.decode(msg.encode(msg.ImageFrame.from_array(_IMG, camera="c", step=0, encoding="jpeg")))
    assert jpeg.to_array().shape == _IMG.shape
    a = msg.ArrayData.of(np.arange(6, dtype=np.float32).reshape(2, 3))
    assert np.array_equal(a.to_array(), np.arange(6, dtype=np.float32).reshape(2, 3))


@pytest.mark.parametrize(
    "payload, fragment",
    [
        (b"", "empty payload"),
        (bytes([msg.PROTOCOL_VERSION + 1]) + ENCODED[0][1:], "protocol version"),
        (ENCODED[0][:-2], "invalid message"),
        (bytes([msg.PROTOCOL_VERSION]) + msgspec.msgpack.encode(["NoSuchMessage", 1]), "invalid message"),
        (
            bytes([msg.PROTOCOL_VERSION])
            + msgspec.msgpack.encode(["EeTarget", 1, [0, 0, float("nan")], 0.5]),
            "finite",
        ),
        (bytes([msg.PROTOCOL_VERSION]) + msgspec.msgpack.encode(["EeTarget", 1, [0, 0, 0], 1.5]), "<= 1.0"),
        (
            bytes([msg.PROTOCOL_VERSION]) + msgspec.msgpack.encode(["JobCancel", "bad/id", ""]),
            "matching regex",
        ),
        (
            bytes([msg.PROTOCOL_VERSION])
            + msgspec.msgpack.encode(["PoseFrame", 0, 0, 0.0, -1, 3, b"x" * 10, [0, 0, 0], 0]),
            "expected 84",
        ),
        (
            bytes([msg.PROTOCOL_VERSION]) + msgspec.msgpack.encode(["EpisodeChunk", "t", 5, 5, b""]),
            "not below",
        ),
        (  # a draft chunk whose arrays do not have one row per state
            bytes([msg.PROTOCOL_VERSION])
            + msgspec.msgpack.encode(
                [
                    "DraftChunk",
                    "s1",
                    "d-1",
                    0,
                    ["float64", [2, 1], bytes(16)],
                    {"time": ["float64", [3], bytes(24)]},
                ]
            ),
            "has",
        ),
        (  # a fork whose states are not float64
            bytes([msg.PROTOCOL_VERSION])
            + msgspec.msgpack.encode(
                [
                    "OpenSession",
                    "pick_place",
                    "panda",
                    "t",
                    0,
                    240,
                    320,
                    ["d-1", ["float32", [1, 2], bytes(8)], {}, 0.0, 0.02, "agent", {}],
                ]
            ),
            "float64",
        ),
    ],
)
def test_invalid_payloads_raise_protocol_error(payload, fragment):
    with pytest.raises(msg.ProtocolError, match=fragment):
        msg.decode(payload)


def test_expect_rejects_the_wrong_type():
    with pytest.raises(msg.ProtocolError, match="expected JobStatus, got Ack"):
        msg.decode(msg.encode(msg.Ack()), msg.JobStatus)


def test_status_rank_orders_attempts_then_phases():
    queued2 = msgspec.structs.replace(_STATUS, state="queued", attempt=3)
    done = msgspec.structs.replace(_STATUS, state="failed")
    assert msg.status_rank(_STATUS) < msg.status_rank(done) < msg.status_rank(queued2)


def test_protocol_doc_embeds_the_generated_tables():
    from studio.backend.protocol_doc import markdown_tables

    doc = (ROOT / "docs" / "protocol.md").read_text()
    assert markdown_tables() in doc, (
        "docs/protocol.md is stale: run `python -m studio.backend.protocol_doc --update docs/protocol.md`"
    )


# ---------------------------------------------------------------------------------------------- fuzzing
def _decode_or_protocol_error(data: bytes) -> None:
    try:
        msg.decode(data)
    except msg.ProtocolError:
        pass


FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(st.binary(max_size=512))
def test_fuzz_random_bytes(data):
    _decode_or_protocol_error(data)
    _decode_or_protocol_error(bytes([msg.PROTOCOL_VERSION]) + data)


@FUZZ
@given(st.sampled_from(ENCODED), st.data())
def test_fuzz_mutated_valid_messages(encoded, data):
    buf = bytearray(encoded)
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert", "delete"]))
        pos = data.draw(st.integers(0, max(0, len(buf) - 1)))
        if op == "flip" and buf:
            buf[pos] ^= data.draw(st.integers(1, 255))
        elif op == "cut":
            del buf[pos:]
        elif op == "insert":
            buf[pos:pos] = data.draw(st.binary(min_size=1, max_size=8))
        elif buf:
            del buf[pos]
    _decode_or_protocol_error(bytes(buf))


_msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70).filter(lambda i: -(2**63) <= i < 2**64)
    | st.floats(allow_nan=True)
    | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=30,
)


@FUZZ
@given(st.sampled_from([t.__name__ for t in msg.MESSAGE_TYPES]), st.lists(_msgpack_values, max_size=14))
def test_fuzz_every_message_tag_with_arbitrary_fields(tag, fields):
    """Every decoder (one per tag) fed structurally valid MessagePack with arbitrary field values."""
    _decode_or_protocol_error(bytes([msg.PROTOCOL_VERSION]) + msgspec.msgpack.encode([tag, *fields]))


@FUZZ
@given(st.sampled_from(EXAMPLES), st.data())
def test_fuzz_one_field_replaced(message, data):
    """A valid message with one field swapped for an arbitrary value is decoded or refused cleanly."""
    fields = [getattr(message, f) for f in message.__struct_fields__]
    if not fields:
        return
    i = data.draw(st.integers(0, len(fields) - 1))
    fields[i] = data.draw(_msgpack_values)
    raw = msgspec.msgpack.encode([type(message).__name__, *[msgspec.to_builtins(f) for f in fields]])
    _decode_or_protocol_error(bytes([msg.PROTOCOL_VERSION]) + raw)


def test_deep_nesting_is_a_protocol_error():
    nested = bytes([msg.PROTOCOL_VERSION]) + b"\x93\xa9JobCancel\xa2j1" + b"\x91" * 100_000 + b"\x01"
    with pytest.raises(msg.ProtocolError):
        msg.decode(nested)
