"""The SQLite catalog: schema, episode queries, runs, checkpoints, rollouts and their summaries."""

from __future__ import annotations

import sqlite3

import pytest
from data_fixtures import make_recording

from studio.data.catalog import (
    Catalog,
    CatalogError,
    CheckpointRecord,
    RolloutRecord,
    RunRecord,
)
from studio.data.episode import Episode


def _meta(task="pick_place/cube->red", robot="panda", role="agent", seed=0, **kw):
    return Episode.from_recording(make_recording(task=task, robot=robot, seed=seed), role=role, **kw).meta


def test_wal_mode_and_schema_version(tmp_path):
    with Catalog(tmp_path / "c.sqlite") as cat:
        assert cat._conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn = sqlite3.connect(tmp_path / "c.sqlite")
    conn.execute("UPDATE schema_info SET value='99' WHERE key='version'")
    conn.commit()
    conn.close()
    with pytest.raises(CatalogError, match="schema version 99"):
        Catalog(tmp_path / "c.sqlite")


def test_not_a_database(tmp_path):
    (tmp_path / "c.sqlite").write_bytes(b"garbage" * 1000)
    with pytest.raises(CatalogError):
        Catalog(tmp_path / "c.sqlite")


def test_episode_queries(tmp_path):
    cat = Catalog(tmp_path / "c.sqlite")
    metas = [
        _meta(seed=0, source="scripted"),
        _meta(seed=1, robot="sawyer", role="expert", source="scripted"),
        _meta(task="pick_place/bar->blue", seed=2, source="teleop"),
        _meta(seed=3, source="scripted", collect_seed=0, collect_index=4),
    ]
    with cat.transaction():
        for m in metas:
            cat.insert_episode(m)
    assert [m.id for m in cat.episodes()] == [m.id for m in metas]
    assert [m.id for m in cat.episodes(newest_first=True, limit=1)] == [metas[-1].id]
    assert {m.id for m in cat.episodes(task="pick_place/cube->red", role="agent")} == {
        metas[0].id,
        metas[3].id,
    }
    assert [m.id for m in cat.episodes(source=["teleop"])] == [metas[2].id]
    assert [m.id for m in cat.episodes(embodiment="sawyer")] == [metas[1].id]
    assert cat.get_episode(metas[1].id) == metas[1]
    assert cat.get_episode("nope") is None
    assert {t.name for t in cat.tasks()} == {"pick_place/cube->red", "pick_place/bar->blue"}
    counts = cat.episode_counts()
    assert counts["pick_place/cube->red"] == {("agent", "panda"): 2, ("expert", "sawyer"): 1}
    assert cat.filled_slots("pick_place/cube->red", "panda", 0) == {4}


def test_transaction_rolls_back(tmp_path):
    cat = Catalog(tmp_path / "c.sqlite")
    m = _meta(source="scripted")
    with pytest.raises(RuntimeError), cat.transaction():
        cat.insert_episode(m)
        raise RuntimeError("boom")
    assert cat.episodes() == []
    with cat.transaction():
        cat.insert_episode(m)
    with pytest.raises(sqlite3.IntegrityError), cat.transaction():
        cat.insert_episode(m)  # same id twice
    assert len(cat.episodes()) == 1


def test_runs_checkpoints_rollouts(tmp_path):
    cat = Catalog(tmp_path / "c.sqlite")
    expert = _meta(robot="sawyer", role="expert", source="scripted")
    with cat.transaction():
        cat.insert_episode(expert)
    cat.add_run(RunRecord(id="run1", name="pp", config={"lr": 1e-4}, dataset_fingerprint="abc"))
    cat.update_run("run1", status="running", started=1.0)
    with pytest.raises(ValueError):
        cat.update_run("run1", status="exploded")
    with pytest.raises(KeyError):
        cat.update_run("nope", status="done")
    assert cat.runs()[0].status == "running"
    assert cat.runs()[0].config == {"lr": 1e-4}
    cat.add_checkpoint(
        CheckpointRecord(id="ck1", run_id="run1", step=100, path="/x/ck1.pt", metrics={"a": 1})
    )
    cat.add_checkpoint(CheckpointRecord(id="ck2", run_id="run1", step=200, path="/x/ck2.pt", is_best=True))
    assert [c.id for c in cat.checkpoints("run1")] == ["ck1", "ck2"]
    assert cat.checkpoints()[1].is_best
    outcomes = [
        ("pick_place/bar->blue", "ck1", True, None),
        ("pick_place/bar->blue", "ck1", False, "grasp"),
        ("pick_place/bar->blue", "ck1", False, "grasp"),
        ("pick_place/bar->blue", "ck2", False, "place"),
        ("pick_place/bar->yellow", "ck1", True, None),
    ]
    for i, (task, ck, ok, stage) in enumerate(outcomes):
        cat.add_rollout(
            RolloutRecord(
                id=f"r{i}",
                task=task,
                checkpoint_id=ck,
                expert_episode_id=expert.id,
                success=ok,
                failure_stage=stage,
                seed=i,
                replans=i,
                planning_time_s=0.5,
                created=float(i),
            )
        )
    failed = cat.rollouts(task="pick_place/bar->blue", checkpoint_id="ck1", success=False)
    assert [r.id for r in failed] == ["r2", "r1"]
    assert failed[0].failure_stage == "grasp"
    summary = {(s["task"], s["checkpoint_id"]): s for s in cat.rollout_summary()}
    s = summary[("pick_place/bar->blue", "ck1")]
    assert (s["rollouts"], s["successes"], s["failures_by_stage"]) == (3, 1, {"grasp": 2})
    assert s["success_rate"] == pytest.approx(1 / 3)
    assert [s["task"] for s in cat.rollout_summary(checkpoint_id="ck2")] == ["pick_place/bar->blue"]
    with pytest.raises(ValueError):
        cat.add_rollout(RolloutRecord(id="bad", task="pick_place/bar->blue", success=True, failure_stage="x"))
    # Deleting the expert episode keeps the rollouts, unlinked.
    with cat.transaction():
        cat.delete_episode(expert.id)
    assert all(r.expert_episode_id is None for r in cat.rollouts())
    # Deleting a run drops its checkpoints; rollouts keep their rows.
    with cat.transaction():
        cat._conn.execute("DELETE FROM runs WHERE id = 'run1'")
    assert cat.checkpoints() == []
    assert len(cat.rollouts()) == 5 and all(r.checkpoint_id is None for r in cat.rollouts())


def test_collection_slots_are_per_role(tmp_path):
    cat = Catalog(tmp_path / "c.sqlite")
    agent = _meta(seed=1, source="scripted", collect_seed=0, collect_index=2)
    expert = _meta(seed=2, role="expert", source="scripted", collect_seed=0, collect_index=2)
    with cat.transaction():
        cat.insert_episode(agent)
        cat.insert_episode(expert)  # the same slot as the agent's, for another role
    with pytest.raises(sqlite3.IntegrityError), cat.transaction():
        cat.insert_episode(_meta(seed=3, source="scripted", collect_seed=0, collect_index=2))
    task = "pick_place/cube->red"
    assert cat.filled_slots(task, "panda", 0, "expert") == cat.filled_slots(task, "panda", 0, "agent") == {2}
    assert cat.filled_slots(task, "panda", 1, "agent") == set()
    assert cat.filled_slots(task, "panda", 0) == {2}


def test_a_catalog_with_slots_without_roles_is_widened_on_open(tmp_path):
    path = tmp_path / "c.sqlite"
    Catalog(path).close()
    conn = sqlite3.connect(path)
    conn.execute("DROP INDEX episodes_by_role_slot")
    conn.execute(
        "CREATE UNIQUE INDEX episodes_by_slot ON episodes(task, embodiment, collect_seed, collect_index) "
        "WHERE collect_index IS NOT NULL"
    )
    conn.commit()
    conn.close()
    cat = Catalog(path)
    names = {r[0] for r in cat._conn.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
    assert "episodes_by_role_slot" in names and "episodes_by_slot" not in names
    with cat.transaction():
        cat.insert_episode(_meta(seed=1, source="scripted", collect_seed=0, collect_index=0))
        cat.insert_episode(_meta(seed=2, role="expert", source="scripted", collect_seed=0, collect_index=0))
    assert len(cat.episodes()) == 2
