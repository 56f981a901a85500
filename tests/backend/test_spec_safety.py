"""Nothing a job spec names reaches pickle or leaves the data dir: checkpoints and decoders load weights-only, every
path resolves inside the worker's data dir (or is a shipped policy), and every spec is typed and bounded on
arrival at the queue."""

from __future__ import annotations

import os
import shutil
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from studio.backend import bus
from studio.backend.job_client import JobClient
from studio.data.store import EpisodeStore

from .conftest import wait_worker

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording

pytestmark = pytest.mark.timeout(180)

POLICY = Path(__file__).resolve().parents[2] / "studio" / "policies" / "pick-place-cpu.pt"


class _Planted:
    """Unpickling this runs a shell command (what a planted checkpoint does)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _plant(path: Path, marker: Path) -> None:
    import torch

    torch.save({"format": "osvi-wm-decoder/1", "payload": _Planted(marker)}, path)


def _planted_checkpoint(where: Path, marker: Path) -> Path:
    """A real checkpoint with a planted decoder beside it (``<stem>.decoder.pt``)."""
    where.mkdir(parents=True, exist_ok=True)
    ck = where / "ck.pt"
    shutil.copy(POLICY, ck)
    _plant(where / "ck.decoder.pt", marker)
    return ck


def test_a_planted_decoder_is_never_unpickled(tmp_path):
    from studio.eval.latents import decode_latents
    from studio.model.train_decoder import load_decoder

    marker = tmp_path / "pwned"
    ck = _planted_checkpoint(tmp_path / "x", marker)
    for load in (
        lambda: decode_latents(ck, np.zeros((3, 8), np.float32)),
        lambda: load_decoder(ck.parent / "ck.decoder.pt"),
    ):
        with pytest.raises(Exception, match=r"(?i)weights.only|unpickl"):
            load()
    assert not marker.exists()


def test_spec_paths_stay_in_the_data_dir(tmp_path):
    from studio.backend.spec_paths import SpecPathError, checkpoint_path, inside_data_dir

    data = tmp_path / "data"
    data.mkdir()
    assert inside_data_dir(data, "runs/a", "run_dir", "train") == data.resolve() / "runs" / "a"
    assert inside_data_dir(data, str(data / "x"), "run_dir", "train") == data.resolve() / "x"
    for bad in ("../../../tmp/x", "/etc", str(data) + "/../y"):
        with pytest.raises(SpecPathError, match="outside the worker's data dir"):
            inside_data_dir(data, bad, "run_dir", "train")
    (data / "link").symlink_to(tmp_path)
    with pytest.raises(SpecPathError, match="outside"):
        inside_data_dir(data, "link/z", "run_dir", "train")
    with pytest.raises(SpecPathError, match="need a worker started with --data-dir"):
        inside_data_dir(None, "x", "run_dir", "train")
    assert checkpoint_path(data, "oracle", "checkpoint", "plan") == "oracle"
    assert checkpoint_path(data, str(POLICY), "checkpoint", "plan") == str(POLICY.resolve())
    assert checkpoint_path(data, "runs/r/best.pt", "checkpoint", "plan") == str(
        data.resolve() / "runs/r/best.pt"
    )
    with pytest.raises(SpecPathError, match=r"neither in the worker's data dir .* nor a shipped policy"):
        checkpoint_path(data, str(tmp_path / "x" / "ck.pt"), "checkpoint", "plan")


def test_a_plan_job_naming_a_planted_checkpoint_outside_the_data_dir_is_refused(hub, workers, tmp_path):
    data = tmp_path / "worker-data"
    with EpisodeStore(data) as store:
        expert = store.add_episode(make_recording(robot="sawyer"), role="expert", source="scripted").id
    marker = tmp_path / "pwned"
    ck = _planted_checkpoint(tmp_path / "planted", marker)
    workers.start(
        "sim", "sim-p", "--data-dir", str(data), handlers=("plan=studio.backend.plan_job:run_plan_job",)
    )
    wait_worker(hub.directory, "sim-p")
    client = JobClient(hub.session)
    spec = {"checkpoint": str(ck), "expert_episode_id": expert, "task": "pick_place/cube->red", "seed": 0}
    for checkpoint in (str(ck), os.path.relpath(ck, data)):
        job = client.submit("plan", {**spec, "checkpoint": checkpoint})
        with client.watch(job.job) as watch:
            final = watch.wait(timeout=120)
        assert final.state == "failed" and "nor a shipped policy" in final.reason, final.reason
        assert "\n" not in final.reason
    assert not marker.exists()
    assert not (data / "plans").exists()


def test_a_train_job_cannot_reach_outside_its_data_dir_and_its_spec_is_bounded(hub, workers, tmp_path):
    data = tmp_path / "trainer-data"
    data.mkdir()
    workers.start("train", "t-safe", "--data-dir", str(data), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "t-safe")
    client = JobClient(hub.session)
    escape = f"../../../tmp/x-{uuid.uuid4().hex}"
    target = (data / escape).resolve()
    job = client.submit("train", {"data_dir": escape, "run_dir": "runs/r", "steps": 2})
    with client.watch(job.job) as watch:
        final = watch.wait(timeout=60)
    assert final.state == "failed" and "outside the worker's data dir" in final.reason, final.reason
    assert "\n" not in final.reason
    assert not target.exists() and not (data / "runs").exists()
    job = client.submit("train", {"data_dir": ".", "run_dir": "/tmp", "steps": 2})
    with client.watch(job.job) as watch:
        assert "run_dir /tmp resolves to" in watch.wait(timeout=60).reason

    # Refused by the queue before anything is queued: bounds and unknown fields, for every kind.
    for kind, spec, fragment in (
        ("train", {"data_dir": ".", "run_dir": "r", "steps": -1}, "steps"),
        ("train", {"data_dir": ".", "run_dir": "r", "steps": 10**12}, "steps"),
        ("train", {"data_dir": ".", "run_dir": "r", "overrides": ["a.b=1"] * 65}, "overrides"),
        ("rollout", {"checkpoint": "oracle", "expert_episode_id": "e", "task": "t", "seed": 0, "x": 1}, "x"),
        ("plan", {"checkpoint": "oracle", "expert_episode_id": "e", "task": "t"}, "seed"),
        ("compare", {"a": "oracle", "b": "oracle", "episodes": 10**6}, "episodes"),
        ("expert", {"task": "pick_place/cube->red", "seed": -3}, "seed"),
        ("collect", {"tasks": ["all"], "episodes": 0}, "episodes"),
    ):
        with pytest.raises(bus.RemoteError, match=rf"bad_request: .*{fragment}") as e:
            client.submit(kind, spec)
        assert "\n" not in e.value.message
    assert not [s for s in client.list() if s.state == "queued"]
