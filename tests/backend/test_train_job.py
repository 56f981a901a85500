"""The `train` job handler on a real trainer worker: the model's training loop driven, reported and cancelled
over the bus, on a small synthetic store."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from studio.backend.job_client import JobClient
from studio.backend.train_job import parse_spec
from studio.data.store import EpisodeStore

from .conftest import wait_worker

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording
from tiny_network import TINY_BATCHED

pytestmark = pytest.mark.timeout(300)

TASKS = ("pick_place/cube->red", "pick_place/cube->green")


@pytest.fixture
def dataset(tmp_path) -> tuple[Path, Path]:
    root = tmp_path / "train-data"
    with EpisodeStore(root) as store:
        seed = 0
        for task in TASKS:
            for robot, role in (("sawyer", "expert"), ("panda", "agent")):
                for _ in range(3):
                    store.add_episode(
                        make_recording(task=task, robot=robot, seed=seed), role=role, source="scripted"
                    )
                    seed += 1
    split = tmp_path / "split.json"
    split.write_text(
        json.dumps({"scene": "pick_place", "train": list(TASKS), "test": [], "val_fraction": 0.0})
    )
    return root, split


def test_spec_is_validated():
    assert parse_spec({"data_dir": "/d", "run_dir": "/r", "steps": 3}).steps == 3
    with pytest.raises(ValueError, match="invalid train job spec"):
        parse_spec({"data_dir": "/d"})
    with pytest.raises(ValueError, match="invalid train job spec"):
        parse_spec({"data_dir": "/d", "run_dir": "/r", "learning_rate": 1})
    spec = parse_spec(
        {"data_dir": "/d", "run_dir": "/r", "recipe": "push", "stage": "grow", "init": "b/best.pt"}
    )
    assert (spec.recipe, spec.stage, spec.scene) == ("push", "grow", None)
    with pytest.raises(ValueError, match="unknown recipe 'pusher'"):
        parse_spec({"data_dir": "/d", "run_dir": "/r", "recipe": "pusher"})
    with pytest.raises(ValueError, match="no stage 'polish'; its stages: base, grow"):
        parse_spec({"data_dir": "/d", "run_dir": "/r", "recipe": "push", "stage": "polish"})
    with pytest.raises(ValueError, match="give the recipe too"):
        parse_spec({"data_dir": "/d", "run_dir": "/r", "stage": "grow"})


def test_train_job_trains_reports_checkpoints_and_cancels(hub, workers, dataset, tmp_path):
    root, split = dataset
    workers.start("train", "gpu-1", "--data-dir", str(tmp_path), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "gpu-1")
    status = hub.directory.get("train", "gpu-1").status
    assert "train" in status.job_kinds, status.unavailable
    client = JobClient(hub.session)
    spec = {
        "data_dir": str(root),
        "run_dir": str(tmp_path / "run"),
        "steps": 4,
        "scene": str(split),
        "overrides": TINY_BATCHED,
        "threads": 1,
    }
    job = client.submit("train", spec)
    assert job.worker_kind == "train" and job.requeue_on_worker_loss
    with client.watch(job.job) as watch:
        final = watch.wait(timeout=240)
        assert final.state == "succeeded", final.reason
        watch.wait(
            lambda w: w.result is not None and any(a.name == "checkpoint:last.pt" for a in w.artifacts), 10
        )
        watch.wait(lambda w: w.progress is not None and w.progress.step == 4, 10)
    assert watch.result.result["status"] == "finished" and watch.result.result["step"] == 4
    assert {"loss", "lr", "samples_per_s"} <= set(watch.progress.metrics) and watch.progress.total == 4
    assert (tmp_path / "run" / "last.pt").exists()

    # A long run, cancelled: stops after writing a checkpoint, reported as cancelled.
    long_spec = {**spec, "run_dir": str(tmp_path / "run-long"), "steps": 10_000}
    job2 = client.submit("train", long_spec)
    with client.watch(job2.job) as watch:
        watch.wait(lambda w: w.progress is not None and w.progress.step >= 2, timeout=240)
        client.cancel(job2.job, reason="enough")
        final = watch.wait(timeout=60)
        watch.wait(lambda w: w.result is not None, 10)
    assert final.state == "cancelled" and "enough" in final.reason
    assert watch.result.result["status"] == "cancelled" and watch.result.result["step"] < 10_000
    assert (tmp_path / "run-long" / "last.pt").exists()
