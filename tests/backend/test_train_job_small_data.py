"""The `train` job on what a user has: a store of two pairs trains with the preset's batch lowered to them (said in
the job's progress and result), a store without a pair fails with what to record, and a fine-tuning job continues
a checkpoint with the short schedule, on a real trainer worker over the bus."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from studio.backend.job_client import JobClient
from studio.backend.train_job import parse_spec
from studio.data.store import EpisodeStore
from studio.model.checkpoint import load_checkpoint
from studio.model.config import FINE_TUNE_LR, FINE_TUNE_STEPS

from .conftest import wait_worker

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording
from tiny_network import TINY

pytestmark = pytest.mark.timeout(400)

RED, GREEN = "pick_place/cube->red", "pick_place/cube->green"


def _split(path: Path) -> Path:
    path.write_text(
        json.dumps({"scene": "pick_place", "train": [RED, GREEN], "test": [], "val_fraction": 0.0})
    )
    return path


def test_a_fine_tuning_spec_names_its_policy_and_fields_are_bounded():
    assert parse_spec({"data_dir": "/d", "run_dir": "/r", "init": "/p.pt", "fine_tune": True}).fine_tune
    for bad in ({"fine_tune": True}, {"steps": 0}, {"config": "huge"}, {"overrides": ["x=1"] * 65}):
        with pytest.raises(ValueError, match="invalid train job spec"):
            parse_spec({"data_dir": "/d", "run_dir": "/r", **bad})


@pytest.mark.slow
def test_two_pairs_train_then_fine_tune_and_an_empty_store_fails_with_what_to_record(hub, workers, tmp_path):
    root = tmp_path / "data"
    with EpisodeStore(
        root
    ) as store:  # cube->red: 1 demonstration × 2 agent episodes; one failed demonstration
        store.add_episode(make_recording(task=RED, robot="sawyer", seed=0), role="expert", source="teleop")
        for seed in (1, 2):
            store.add_episode(
                make_recording(task=RED, robot="panda", seed=seed), role="agent", source="teleop"
            )
        rec = make_recording(task=GREEN, robot="sawyer", seed=3, success=False)
        store.add_episode(rec, role="expert", source="teleop")
    split = _split(tmp_path / "split.json")
    workers.start("train", "trainer-1", "--data-dir", str(tmp_path), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "trainer-1")
    client = JobClient(hub.session)

    spec = {"data_dir": str(root), "run_dir": str(tmp_path / "base"), "steps": 3, "scene": str(split)}
    spec.update(overrides=TINY, threads=1)
    job = client.submit("train", spec)
    with client.watch(job.job) as watch:
        final = watch.wait(timeout=300)
        assert final.state == "succeeded", final.reason
        watch.wait(lambda w: w.result is not None, 10)
    result = watch.result.result
    assert (result["status"], result["step"], result["pairs"], result["batch_size"]) == ("finished", 3, 2, 2)
    assert result["notes"] == ["batch size 16 lowered to 2: there are only 2 training pairs"]

    tuned = {"data_dir": str(root), "run_dir": str(tmp_path / "tuned"), "scene": str(split), "threads": 1}
    tuned.update(init=str(tmp_path / "base" / "last.pt"), fine_tune=True)
    job = client.submit("train", tuned)
    with client.watch(job.job) as watch:
        final = watch.wait(timeout=300)
        assert final.state == "succeeded", final.reason
        watch.wait(lambda w: w.result is not None, 10)
    assert watch.result.result["step"] == FINE_TUNE_STEPS[0] and watch.result.result["batch_size"] == 2
    ckpt = load_checkpoint(tmp_path / "tuned" / "last.pt")
    assert ckpt["config"]["train"]["lr_max"] == FINE_TUNE_LR
    assert tuple(ckpt["config"]["model"]["image_size"]) == (48, 64)

    empty = tmp_path / "empty"
    EpisodeStore(empty).close()
    job = client.submit("train", {**spec, "data_dir": str(empty), "run_dir": str(tmp_path / "nothing")})
    with client.watch(job.job) as watch:
        final = watch.wait(timeout=120)
    assert final.state == "failed" and "record a successful demonstration" in final.reason
    assert not (tmp_path / "nothing" / "last.pt").exists()
