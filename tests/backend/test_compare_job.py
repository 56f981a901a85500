"""The `compare` job on a real sim worker: progress per episode, the table's rows as the result, every rollout
stored; a bad spec fails with the reason; a killed worker fails the job and leaves no result."""

from __future__ import annotations

import signal
import time

import pytest

from studio.backend import bus
from studio.backend.job_client import JobClient
from studio.data.collect import CollectConfig, collect
from studio.data.store import EpisodeStore
from studio.eval.compare import stored_evaluations

from .conftest import wait_worker

pytestmark = pytest.mark.timeout(300)
TASK = "pick_place/bar->blue"


def _mid_way(w) -> bool:
    """At least one episode of three done, not all of them."""
    return w.progress is not None and w.progress.message.startswith(("episode 1 of 3", "episode 2 of 3"))


@pytest.fixture
def root(tmp_path):
    root = tmp_path / "data"
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=[TASK],
            episodes=2,
            data_dir=str(root),
            progress=False,
            image_size=(120, 160),
        )
    )
    return root


def test_compare_job_reports_each_episode_and_returns_the_rows(hub, workers, root):
    workers.start("sim", "sim-c", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-c")
    assert "compare" in hub.directory.get("sim", "sim-c").status.job_kinds
    client = JobClient(hub.session)
    messages: list[str] = []
    job = client.submit(
        "compare",
        {"a": "oracle", "b": "oracle", "label_b": "oracle 2", "tasks": [TASK], "episodes": 2, "seed": 3},
    )
    with client.watch(job.job, on_progress=lambda p: messages.append(p.message)) as w:
        final = w.wait(timeout=180)
        assert final.state == "succeeded", final.reason
        w.wait(lambda w: w.result is not None, 10)
    result = w.result.result
    # (The first message, "starting: …", may go out before the watch subscribes: progress keeps only the latest.)
    assert "episode 1 of 2: A ✔, B ✔" in messages and "episode 2 of 2: A ✔, B ✔" in messages
    assert [r["difference"] for r in result["rows"]] == ["both", "both"]
    assert result["totals"]["a_success"] == 1.0 and result["label_b"] == "oracle 2"
    assert "| A: oracle | B: oracle 2 | difference |" in result["markdown"]
    with EpisodeStore(root) as store:
        for side, eval_id in zip("ab", result["eval_ids"], strict=True):
            rows = store.catalog.rollouts(eval_id=eval_id)
            assert sorted(r.id for r in rows) == sorted(r[side]["rollout_id"] for r in result["rows"])
            assert all(r.episode_id is not None for r in rows)


def test_bad_compare_specs_fail_with_the_reason(hub, workers, root):
    workers.start("sim", "sim-d", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-d")
    client = JobClient(hub.session)
    with pytest.raises(bus.RemoteError, match=r"bad_request: compare job spec lacks \['b'\]"):  # on arrival
        client.submit("compare", {"a": "oracle"})
    for spec, says in (
        ({"a": "oracle", "b": "oracle", "tasks": "pick_place/ball->red"}, "unknown task"),
        ({"a": "missing.pt", "b": "oracle", "tasks": [TASK]}, "no checkpoint file"),
    ):
        job = client.submit("compare", spec)
        with client.watch(job.job) as w:
            final = w.wait(timeout=60)
        assert final.state == "failed" and says in final.reason, final.reason


def test_sim_worker_killed_mid_compare_fails_the_job_and_leaves_no_result(hub, workers, root):
    proc = workers.start("sim", "sim-k", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-k")
    client = JobClient(hub.session)
    job = client.submit("compare", {"a": "oracle", "b": "oracle", "tasks": [TASK], "episodes": 3, "seed": 1})
    with client.watch(job.job) as w:
        w.wait(_mid_way, timeout=120)
        t_kill = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        final = w.wait(timeout=5)
        elapsed = time.monotonic() - t_kill
        time.sleep(0.5)
        assert w.result is None, "a lost comparison has no result"
    assert final.state == "failed" and "lost" in final.reason and elapsed < 5.0
    with EpisodeStore(root) as store:
        evals = stored_evaluations(store.catalog)
    assert evals and not any(e.complete for e in evals), (
        "what it stored says it is part of an unfinished comparison"
    )


def test_a_cancelled_compare_ends_as_cancelled(hub, workers, root):
    workers.start("sim", "sim-x", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-x")
    client = JobClient(hub.session)
    job = client.submit("compare", {"a": "oracle", "b": "oracle", "tasks": [TASK], "episodes": 3, "seed": 2})
    with client.watch(job.job) as w:
        w.wait(_mid_way, timeout=120)
        client.cancel(job.job, "changed my mind")
        final = w.wait(timeout=30)
    assert final.state == "cancelled" and w.result is None
