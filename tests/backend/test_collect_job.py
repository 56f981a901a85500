"""The `collect` job on a real sim worker: scripted episodes stored with progress, resumed, cancelled mid-way, and bad
specs refused on arrival with one line naming the field."""

from __future__ import annotations

import typing

import pytest

from studio.backend import bus
from studio.backend.collect_job import Robot, SpecError, check_spec
from studio.backend.job_client import JobClient, new_job_id
from studio.backend.job_runner import JOB_KINDS
from studio.data.collect import ROLE_OF_ROBOT
from studio.data.store import EpisodeStore

from .conftest import wait_worker

pytestmark = pytest.mark.timeout(300)
TASKS = ["pick_place/cube->red", "pick_place/bar->blue"]  # a training task and a held-out one
#: Bad specs and the field their one-line refusal names.
BAD = [
    ({"tasks": ["pick_place/cube->purple"]}, "tasks", "unknown task"),
    ({"tasks": ["push/red-forward"]}, "tasks", "belongs to scene 'push'"),
    ({"tasks": TASKS[:1], "episodes": 10**9}, "episodes", "<= 200, got 1000000000"),
    ({"tasks": TASKS[:1], "seed": -1}, "seed", ">= 0, got -1"),
    ({"tasks": TASKS[:1], "robot": "hand", "role": "agent"}, "role", "only demonstrates"),
    ({"tasks": ["metaworld/reach-v2"], "scene": "metaworld", "robot": "panda"}, "robot", "only the Sawyer"),
    ({"tasks": TASKS[:1], "workers": 8}, "workers", "not a field"),
    ({"tasks": []}, "tasks", "length >= 1"),
]


def test_spec_is_typed_bounded_and_resolved():
    assert JOB_KINDS["collect"].worker_kind == "sim" and JOB_KINDS["collect"].requeue_on_worker_loss
    assert set(typing.get_args(Robot)) == set(ROLE_OF_ROBOT)
    spec = check_spec({"tasks": ["held-out"], "robot": "panda"})
    assert spec.tasks == ["pick_place/bar->blue", "pick_place/bar->yellow"] and spec.role == "agent"
    assert (spec.scene, spec.episodes, spec.seed) == ("pick_place", 10, 0)
    assert check_spec({"tasks": TASKS, "robot": "hand", "episodes": 200}).role == "expert"
    for raw, field, words in BAD:
        with pytest.raises(SpecError) as e:
            check_spec(raw)
        text = str(e.value)
        assert text.startswith(f"collect job spec: {field}: ") and words in text and "\n" not in text, text


def _events(client: JobClient, spec: dict, *, cancel_after: int | None = None, timeout: float = 120):
    """Run a collect job; returns (final status, result, progress records). ``cancel_after``: cancel once that many
    episodes are done."""
    progress: list = []
    job = new_job_id("collect")
    cancelled = False
    with client.watch(job, on_progress=progress.append) as w:  # before the job starts: every progress record
        client.submit("collect", spec, job=job)
        if cancel_after is not None:
            w.wait(lambda w: w.progress is not None and w.progress.step >= cancel_after, timeout)
            client.cancel(job, "enough")
            cancelled = True
        final = w.wait(timeout=timeout)
        if final.state != "failed":
            w.wait(lambda w: w.result is not None, 10)
    assert cancelled == (cancel_after is not None)
    return final, (w.result.result if w.result else None), progress


def test_collect_job_stores_episodes_with_progress_resumes_and_cancels(hub, workers, tmp_path):
    root = tmp_path / "data"
    workers.start("sim", "sim-c", "--data-dir", str(root), handlers=(), only_handlers=False)
    wait_worker(hub.directory, "sim-c")
    status = hub.directory.get("sim", "sim-c").status
    assert "collect" in status.job_kinds, status.unavailable
    client = JobClient(hub.session)

    # Refused on arrival, before anything is simulated: failed, with the one line naming the field.
    for raw, field, words in BAD[:4]:  # refused by the queue on arrival, with the worker's one line
        with pytest.raises(bus.RemoteError) as e:
            client.submit("collect", {"scene": "pick_place", **raw})
        text = e.value.message
        assert (
            e.value.code == "bad_request"
            and text.startswith(f"collect job spec: {field}: ")
            and words in text
        )
    assert not EpisodeStore(root).episodes()

    # Two episodes of each of two tasks (one held out, as studio collect allows for demonstrations).
    spec = {"scene": "pick_place", "robot": "sawyer", "tasks": TASKS, "episodes": 2, "seed": 3}
    final, result, progress = _events(client, spec)
    assert final.state == "succeeded", final.reason
    assert (result["requested"], result["made"], result["already_present"], result["stopped"]) == (
        4,
        2 * 2,
        0,
        False,
    )
    assert result["role"] == "expert" and result["tasks"] == TASKS
    steps = [(p.step, p.total) for p in progress]
    assert steps[0] == (0, 4) and steps[-1] == (4, 4) and [s for s, _ in steps] == sorted(s for s, _ in steps)
    assert any(p.message.startswith("episode 4 of 4: ") for p in progress), [p.message for p in progress]
    with EpisodeStore(root) as store:
        metas = store.episodes()
        assert sorted((m.task, m.collect_index) for m in metas) == sorted(
            (t, i) for t in TASKS for i in (0, 1)
        )
        assert all(
            (m.role, m.source, m.embodiment, m.collect_seed, m.success)
            == ("expert", "scripted", "sawyer", 3, True)
            for m in metas
        )

    # The same spec again makes nothing: its slots are filled.
    final, result, progress = _events(client, spec)
    assert final.state == "succeeded" and (result["made"], result["already_present"]) == (0, 4)
    assert progress[0].step == progress[0].total == 4

    # Cancelled mid-way: the episodes stored stay, whole; none is half-written; the result says what is left.
    many = {"scene": "pick_place", "robot": "panda", "tasks": TASKS[:1], "episodes": 60, "seed": 0}
    final, result, progress = _events(client, many, cancel_after=2)
    assert final.state == "cancelled" and final.reason == "enough", final.reason
    assert result["stopped"] and 2 <= result["made"] < 60 and result["left"] == 60 - result["made"]
    with EpisodeStore(root) as store:
        agents = store.episodes(role="agent")
        assert len(agents) == result["made"] and all(m.embodiment == "panda" for m in agents)
        assert store.check(clean=False).ok
        for m in agents:
            assert store.load_frames(m.id).shape[0] == m.num_frames
