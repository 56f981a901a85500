"""The runs table's step and kind for runs cut short or fine-tuned, and the pace the Train tab estimates wall time
from."""

from __future__ import annotations

import json

from studio.ui.runs import RunRegistry


def _run(root, name, rows, *, spec=None, batch_size=16):
    d = root / "runs" / name
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"config": {"train": {"batch_size": batch_size}}, "tasks": []}))
    (d / "spec.json").write_text(json.dumps(spec or {"config": "cpu"}))
    (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    return d


def test_a_run_cancelled_between_two_records_shows_the_step_it_reached(tmp_path):
    _run(
        tmp_path,
        "train-a",
        [
            {"event": "start", "step": 0, "total_steps": 20, "time": 1.0},
            {"event": "end", "status": "cancelled", "step": 3, "time": 2.0},
        ],
    )
    (run,) = RunRegistry(tmp_path).runs()
    assert (run.step, run.total, run.ended) == (3, 20, "cancelled")


def test_a_run_whose_step_raised_shows_failed(tmp_path):
    _run(
        tmp_path,
        "train-b",
        [
            {"event": "start", "step": 0, "total_steps": 20, "time": 1.0},
            {"step": 1, "loss": 1.0, "lr": 1e-4},
            {"event": "end", "status": "failed", "step": 2, "error": "boom", "time": 2.0},
        ],
    )
    (run,) = RunRegistry(tmp_path).runs()
    assert (run.step, run.ended) == (2, "failed")


def test_fine_tuning_runs_are_named_and_the_pace_is_per_kind_and_batch(tmp_path):
    reg = RunRegistry(tmp_path)
    assert reg.step_seconds("cpu", 16) is None
    start = {"event": "start", "step": 0, "total_steps": 4, "time": 1.0}
    _run(tmp_path, "train-1", [start, *({"step": s, "loss": 1.0, "samples_per_s": 8.0} for s in (1, 2, 3))])
    _run(
        tmp_path,
        "train-2",
        [start, {"step": 1, "loss": 1.0, "samples_per_s": 2.0}],
        spec={"config": "cpu", "fine_tune": True, "init": "p.pt"},
        batch_size=8,
    )
    assert [r.config for r in reg.runs()] == ["cpu", "fine-tune"]
    assert reg.step_seconds("cpu", 16) == (2.0, "train-1")  # 16 pairs a step at 8 pairs/s
    assert reg.step_seconds("fine-tune", 8) == (4.0, "train-2")
    assert reg.step_seconds("cpu", 4) is None and reg.step_seconds("paper", 16) is None
