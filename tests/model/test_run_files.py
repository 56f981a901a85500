"""Run-directory bookkeeping: metrics trimming on resume, atomic writes, step seeds, cancellation flags."""

from __future__ import annotations

import json
import threading

from studio.model.run_files import (
    append_jsonl,
    atomic_save,
    is_cancelled,
    step_seed,
    trim_metrics,
    write_json,
)


def test_trim_metrics_drops_later_steps_and_torn_lines(tmp_path):
    path = tmp_path / "metrics.jsonl"
    for step in (0, 5, 10, 15):
        append_jsonl(path, {"step": step})
    with open(path, "a") as f:
        f.write('{"step": 2')  # cut short by a kill
    trim_metrics(path, 10)
    assert [json.loads(line)["step"] for line in path.read_text().splitlines()] == [0, 5, 10]
    trim_metrics(path, 0)
    assert not path.exists()


def test_atomic_writes_leave_no_temporary_files(tmp_path):
    atomic_save({"a": 1}, tmp_path / "x.pt")
    write_json(tmp_path / "c.json", {"b": 2})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json", "x.pt"]


def test_step_seeds_differ_per_step_and_rank_and_repeat():
    assert step_seed(0, 1) == step_seed(0, 1)
    assert len({step_seed(0, s, r) for s in range(20) for r in range(2)}) == 40


def test_cancellation_accepts_events_and_callables():
    event = threading.Event()
    assert not is_cancelled(event) and not is_cancelled(None)
    event.set()
    assert is_cancelled(event) and is_cancelled(lambda: True)
