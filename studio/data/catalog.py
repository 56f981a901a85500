"""The SQLite catalog: an index of tasks, episodes, training runs, checkpoints and rollouts.

The catalog is the single source of truth for *which* episodes exist (files on disk are only visible
through a row here) and answers the UI's questions from indexes, e.g. "failed rollouts of task X by
checkpoint Y" or "how many agent episodes does each task have". It runs in WAL mode with
``synchronous=FULL`` so that readers never block the writer, several processes can write (each in a
short ``BEGIN IMMEDIATE`` transaction), and a committed row survives a crash.

Schema (version 1)::

    tasks(name PK, scene, description)
    episodes(seq PK autoincrement, id UNIQUE, task -> tasks, scene, embodiment, role, source, seed,
             success, created, num_frames, num_steps, height, width, fps, control_dt,
             collect_seed, collect_index, meta_json)
        unique (task, embodiment, role, collect_seed, collect_index) for scripted-collection slots (a
        catalog whose slots predate the role, unique per (task, embodiment, collect_seed, collect_index), is
        widened on open: that index is replaced, no row changes)
    runs(id PK, name, scene, status, config_json, dataset_fingerprint, created, started, finished,
         path, error)
    checkpoints(id PK, run_id -> runs (cascade), step, epoch, created, path, val_loss, metrics_json,
                is_best)
    rollouts(id PK, task -> tasks, checkpoint_id -> checkpoints, expert_episode_id -> episodes,
             episode_id -> episodes (the stored rollout recording), robot, seed, success, failure_stage,
             replans, planning_time_s, duration_s, num_steps, created, path, eval_id, extra_json)
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from studio.data.episode import EMBODIMENTS, ROLES, SOURCES, EpisodeMeta, scene_of_task

SCHEMA_VERSION = 1
RUN_STATUSES = ("queued", "running", "done", "failed", "cancelled")


def _in(values: Sequence[str]) -> str:
    return "(" + ", ".join(f"'{v}'" for v in values) + ")"


_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS schema_info (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tasks (
    name TEXT PRIMARY KEY,
    scene TEXT NOT NULL,
    description TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS episodes (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    task TEXT NOT NULL REFERENCES tasks(name),
    scene TEXT NOT NULL,
    embodiment TEXT NOT NULL CHECK (embodiment IN {_in(EMBODIMENTS)}),
    role TEXT NOT NULL CHECK (role IN {_in(ROLES)}),
    source TEXT NOT NULL CHECK (source IN {_in(SOURCES)}),
    seed INTEGER,
    success INTEGER,
    created REAL NOT NULL,
    num_frames INTEGER NOT NULL,
    num_steps INTEGER NOT NULL,
    height INTEGER NOT NULL,
    width INTEGER NOT NULL,
    fps REAL NOT NULL,
    control_dt REAL,
    collect_seed INTEGER,
    collect_index INTEGER,
    meta_json TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS episodes_by_task ON episodes(task, role, embodiment, success);
CREATE INDEX IF NOT EXISTS episodes_by_source ON episodes(source, created);
DROP INDEX IF EXISTS episodes_by_slot;
CREATE UNIQUE INDEX IF NOT EXISTS episodes_by_role_slot
    ON episodes(task, embodiment, role, collect_seed, collect_index) WHERE collect_index IS NOT NULL;
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL DEFAULT '',
    scene TEXT,
    status TEXT NOT NULL CHECK (status IN {_in(RUN_STATUSES)}),
    config_json TEXT NOT NULL DEFAULT '{{}}',
    dataset_fingerprint TEXT,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    path TEXT,
    error TEXT
);
CREATE INDEX IF NOT EXISTS runs_by_created ON runs(created);
CREATE TABLE IF NOT EXISTS checkpoints (
    id TEXT PRIMARY KEY,
    run_id TEXT NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    step INTEGER NOT NULL,
    epoch REAL,
    created REAL NOT NULL,
    path TEXT NOT NULL,
    val_loss REAL,
    metrics_json TEXT NOT NULL DEFAULT '{{}}',
    is_best INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS checkpoints_by_run ON checkpoints(run_id, step);
CREATE TABLE IF NOT EXISTS rollouts (
    id TEXT PRIMARY KEY,
    task TEXT NOT NULL REFERENCES tasks(name),
    checkpoint_id TEXT REFERENCES checkpoints(id) ON DELETE SET NULL,
    expert_episode_id TEXT REFERENCES episodes(id) ON DELETE SET NULL,
    episode_id TEXT REFERENCES episodes(id) ON DELETE SET NULL,
    robot TEXT,
    seed INTEGER,
    success INTEGER NOT NULL,
    failure_stage TEXT,
    replans INTEGER NOT NULL DEFAULT 0,
    planning_time_s REAL,
    duration_s REAL,
    num_steps INTEGER,
    created REAL NOT NULL,
    path TEXT,
    eval_id TEXT,
    extra_json TEXT NOT NULL DEFAULT '{{}}'
);
CREATE INDEX IF NOT EXISTS rollouts_by_task ON rollouts(task, checkpoint_id, success);
CREATE INDEX IF NOT EXISTS rollouts_by_checkpoint ON rollouts(checkpoint_id, success, failure_stage);
CREATE INDEX IF NOT EXISTS rollouts_by_eval ON rollouts(eval_id);
CREATE INDEX IF NOT EXISTS rollouts_by_expert ON rollouts(expert_episode_id);
"""


class CatalogError(RuntimeError):
    """The catalog file is unusable (wrong schema version, not a database, ...)."""


@dataclass(frozen=True)
class TaskRecord:
    name: str
    scene: str
    description: str = ""


@dataclass
class RunRecord:
    """A training run. ``config`` is the run's full configuration (JSON-serialisable)."""

    id: str
    status: str = "queued"
    name: str = ""
    scene: str | None = None
    config: dict = field(default_factory=dict)
    dataset_fingerprint: str | None = None
    created: float = field(default_factory=time.time)
    started: float | None = None
    finished: float | None = None
    path: str | None = None
    error: str | None = None


@dataclass
class CheckpointRecord:
    """A saved model of a run; ``path`` is the checkpoint file, ``metrics`` any scalar results."""

    id: str
    run_id: str
    step: int
    path: str
    epoch: float | None = None
    created: float = field(default_factory=time.time)
    val_loss: float | None = None
    metrics: dict = field(default_factory=dict)
    is_best: bool = False


@dataclass
class RolloutRecord:
    """One imitation attempt: a checkpoint shown an expert episode, acting in a seeded scene.

    Attributes:
        failure_stage: None on success; otherwise where it failed (e.g. ``"reach"``, ``"grasp"``,
            ``"transport"``, ``"place"``, ``"timeout"``).
        episode_id: the stored recording of the rollout (an agent episode, source ``"rollout"``), if kept.
        path: directory of the rollout's other files (plans, waypoints, decoded latent images).
        eval_id: groups the rollouts of one evaluation job.
    """

    id: str
    task: str
    success: bool
    checkpoint_id: str | None = None
    expert_episode_id: str | None = None
    episode_id: str | None = None
    robot: str | None = None
    seed: int | None = None
    failure_stage: str | None = None
    replans: int = 0
    planning_time_s: float | None = None
    duration_s: float | None = None
    num_steps: int | None = None
    created: float = field(default_factory=time.time)
    path: str | None = None
    eval_id: str | None = None
    extra: dict = field(default_factory=dict)


_EPISODE_COLUMNS = (
    "id task scene embodiment role source seed success created num_frames num_steps height width fps "
    "control_dt collect_seed collect_index"
).split()


def _rollout(row: sqlite3.Row) -> RolloutRecord:
    d = dict(row)
    d["extra"] = json.loads(d.pop("extra_json"))
    d["success"] = bool(d["success"])
    return RolloutRecord(**d)


def _bool_or_none(v):
    return None if v is None else bool(v)


class Catalog:
    """A connection to the catalog database; safe to share between threads of one process.

    Each process opens its own :class:`Catalog`; SQLite's locking serialises writers across processes.
    """

    def __init__(self, path: str | Path, timeout_s: float = 60.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        try:
            self._conn = sqlite3.connect(
                str(self.path), timeout=timeout_s, isolation_level=None, check_same_thread=False
            )
            self._conn.row_factory = sqlite3.Row
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute("PRAGMA synchronous=FULL")
            self._conn.execute("PRAGMA foreign_keys=ON")
            with self.transaction():
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        self._conn.execute(statement)
                row = self._conn.execute("SELECT value FROM schema_info WHERE key='version'").fetchone()
                if row is None:
                    self._conn.execute(
                        "INSERT INTO schema_info(key, value) VALUES ('version', ?)", (str(SCHEMA_VERSION),)
                    )
                elif int(row[0]) != SCHEMA_VERSION:
                    raise CatalogError(
                        f"{self.path}: catalog schema version {row[0]}, this studio reads {SCHEMA_VERSION}"
                    )
        except sqlite3.DatabaseError as e:
            raise CatalogError(f"{self.path}: cannot open the catalog ({e})") from e

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """A write transaction (``BEGIN IMMEDIATE``): everything inside commits together or not at all."""
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            else:
                self._conn.execute("COMMIT")

    def _query(self, sql: str, params: Sequence = ()) -> list[sqlite3.Row]:
        with self._lock:
            return self._conn.execute(sql, tuple(params)).fetchall()

    # ------------------------------------------------------------------ tasks
    def ensure_task(self, name: str, scene: str | None = None, description: str = "") -> None:
        """Register a task if it is not known yet (call inside or outside a transaction)."""
        with self._lock:
            self._conn.execute(
                "INSERT OR IGNORE INTO tasks(name, scene, description) VALUES (?, ?, ?)",
                (name, scene or scene_of_task(name), description),
            )

    def tasks(self, scene: str | None = None) -> list[TaskRecord]:
        sql, params = "SELECT name, scene, description FROM tasks", []
        if scene is not None:
            sql, params = sql + " WHERE scene = ?", [scene]
        return [TaskRecord(*r) for r in self._query(sql + " ORDER BY name", params)]

    def episode_counts(self, scene: str | None = None) -> dict[str, dict[tuple[str, str], int]]:
        """Per task: number of episodes for each (role, embodiment)."""
        sql = "SELECT task, role, embodiment, COUNT(*) FROM episodes"
        params: list = []
        if scene is not None:
            sql, params = sql + " WHERE scene = ?", [scene]
        out: dict[str, dict[tuple[str, str], int]] = {}
        for task, role, emb, n in self._query(sql + " GROUP BY task, role, embodiment", params):
            out.setdefault(task, {})[(role, emb)] = n
        return out

    # ------------------------------------------------------------------ episodes
    def insert_episode(self, meta: EpisodeMeta) -> None:
        """Add an episode row (and its task). Call inside :meth:`transaction` together with the files' move."""
        self.ensure_task(meta.task, meta.scene)
        values = [getattr(meta, c) for c in _EPISODE_COLUMNS]
        values[_EPISODE_COLUMNS.index("success")] = None if meta.success is None else int(meta.success)
        with self._lock:
            self._conn.execute(
                f"INSERT INTO episodes({', '.join(_EPISODE_COLUMNS)}, meta_json) "
                f"VALUES ({', '.join('?' * (len(_EPISODE_COLUMNS) + 1))})",
                (*values, json.dumps(meta.to_dict(), sort_keys=True)),
            )

    def delete_episode(self, episode_id: str) -> bool:
        """Remove an episode row; True if it existed. Rollouts referring to it keep their row (NULL link)."""
        with self._lock:
            cur = self._conn.execute("DELETE FROM episodes WHERE id = ?", (episode_id,))
            return cur.rowcount > 0

    def get_episode(self, episode_id: str) -> EpisodeMeta | None:
        rows = self._query("SELECT meta_json FROM episodes WHERE id = ?", (episode_id,))
        return EpisodeMeta.from_dict(json.loads(rows[0][0])) if rows else None

    def episodes(
        self,
        task: str | None = None,
        tasks: Sequence[str] | None = None,
        scene: str | None = None,
        role: str | Sequence[str] | None = None,
        embodiment: str | Sequence[str] | None = None,
        source: str | Sequence[str] | None = None,
        success: bool | None = None,
        newest_first: bool = False,
        limit: int | None = None,
    ) -> list[EpisodeMeta]:
        """Episodes matching every given filter, in insertion order (or newest first)."""
        where: list[str] = []
        params: list[str | int] = []
        if task is not None:
            where.append("task = ?")
            params.append(task)
        if tasks is not None:
            where.append(f"task IN ({', '.join('?' * len(tasks))})")
            params.extend(tasks)
        for col, val in (("scene", scene), ("role", role), ("embodiment", embodiment), ("source", source)):
            if val is None:
                continue
            vals = [val] if isinstance(val, str) else list(val)
            where.append(f"{col} IN ({', '.join('?' * len(vals))})")
            params.extend(vals)
        if success is not None:
            where.append("success = ?")
            params.append(int(success))
        sql = "SELECT meta_json FROM episodes"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY seq" + (" DESC" if newest_first else "")
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        return [EpisodeMeta.from_dict(json.loads(r[0])) for r in self._query(sql, params)]

    def episode_ids(self) -> set[str]:
        return {r[0] for r in self._query("SELECT id FROM episodes")}

    def filled_slots(
        self, task: str, embodiment: str, collect_seed: int, role: str | None = None
    ) -> set[int]:
        """Indices of a scripted collection run (task, embodiment, base seed; and role unless None) that already
        have an episode."""
        sql = "SELECT collect_index FROM episodes WHERE task = ? AND embodiment = ? AND collect_seed = ?"
        params: list[str | int] = [task, embodiment, collect_seed]
        if role is not None:
            sql, params = sql + " AND role = ?", [*params, role]
        rows = self._query(sql, params)
        return {int(r[0]) for r in rows}

    # ------------------------------------------------------------------ runs and checkpoints
    def add_run(self, run: RunRecord) -> None:
        if run.status not in RUN_STATUSES:
            raise ValueError(f"run status must be one of {RUN_STATUSES}, got {run.status!r}")
        d = asdict(run)
        d["config_json"] = json.dumps(d.pop("config"), sort_keys=True)
        self._insert("runs", d)

    def update_run(self, run_id: str, **changes) -> None:
        """Change fields of a run, e.g. ``update_run(id, status="done", finished=time.time())``."""
        if "status" in changes and changes["status"] not in RUN_STATUSES:
            raise ValueError(f"run status must be one of {RUN_STATUSES}, got {changes['status']!r}")
        if "config" in changes:
            changes["config_json"] = json.dumps(changes.pop("config"), sort_keys=True)
        allowed = {f.name for f in fields(RunRecord)} - {"id", "config"} | {"config_json"}
        bad = set(changes) - allowed
        if bad:
            raise ValueError(f"unknown run fields {sorted(bad)}")
        with self._lock:
            cur = self._conn.execute(
                f"UPDATE runs SET {', '.join(f'{k} = ?' for k in changes)} WHERE id = ?",
                (*changes.values(), run_id),
            )
            if cur.rowcount == 0:
                raise KeyError(f"no run {run_id!r}")

    def runs(self, status: str | None = None) -> list[RunRecord]:
        sql, params = "SELECT * FROM runs", []
        if status is not None:
            sql, params = sql + " WHERE status = ?", [status]
        out = []
        for r in self._query(sql + " ORDER BY created", params):
            d = dict(r)
            d["config"] = json.loads(d.pop("config_json"))
            out.append(RunRecord(**d))
        return out

    def add_checkpoint(self, ck: CheckpointRecord) -> None:
        d = asdict(ck)
        d["metrics_json"] = json.dumps(d.pop("metrics"), sort_keys=True)
        d["is_best"] = int(d["is_best"])
        self._insert("checkpoints", d)

    def has_checkpoint(self, checkpoint_id: str) -> bool:
        return bool(self._query("SELECT 1 FROM checkpoints WHERE id = ?", [checkpoint_id]))

    def ensure_checkpoint(self, ck: CheckpointRecord, run: RunRecord) -> None:
        """Add ``ck``, and ``run`` (its run) if the catalog lacks that run, unless ``ck.id`` is already known
        (then nothing is rewritten). Rollouts refer to checkpoints by id, so register before storing them."""
        if ck.run_id != run.id:
            raise ValueError(f"checkpoint {ck.id!r} belongs to run {ck.run_id!r}, not {run.id!r}")
        with self.transaction():
            if self.has_checkpoint(ck.id):
                return
            if not self._query("SELECT 1 FROM runs WHERE id = ?", [run.id]):
                self.add_run(run)
            self.add_checkpoint(ck)

    def checkpoints(self, run_id: str | None = None) -> list[CheckpointRecord]:
        sql, params = "SELECT * FROM checkpoints", []
        if run_id is not None:
            sql, params = sql + " WHERE run_id = ?", [run_id]
        out = []
        for r in self._query(sql + " ORDER BY run_id, step", params):
            d = dict(r)
            d["metrics"] = json.loads(d.pop("metrics_json"))
            d["is_best"] = bool(d["is_best"])
            out.append(CheckpointRecord(**d))
        return out

    # ------------------------------------------------------------------ rollouts
    def add_rollout(self, r: RolloutRecord) -> None:
        """Add a rollout row (and its task). May run inside a transaction with the rollout's episode."""
        if r.success and r.failure_stage is not None:
            raise ValueError("a successful rollout has no failure stage")
        self.ensure_task(r.task)
        d = asdict(r)
        d["extra_json"] = json.dumps(d.pop("extra"), sort_keys=True)
        d["success"] = int(d["success"])
        self._insert("rollouts", d)

    def rollouts(
        self,
        task: str | None = None,
        checkpoint_id: str | None = None,
        success: bool | None = None,
        failure_stage: str | None = None,
        expert_episode_id: str | None = None,
        eval_id: str | None = None,
        limit: int | None = None,
    ) -> list[RolloutRecord]:
        """Rollouts matching every given filter, newest first."""
        where: list[str] = []
        params: list[str | int] = []
        for col, val in (
            ("task", task),
            ("checkpoint_id", checkpoint_id),
            ("failure_stage", failure_stage),
            ("expert_episode_id", expert_episode_id),
            ("eval_id", eval_id),
        ):
            if val is not None:
                where.append(f"{col} = ?")
                params.append(val)
        if success is not None:
            where.append("success = ?")
            params.append(int(success))
        sql = "SELECT * FROM rollouts" + (" WHERE " + " AND ".join(where) if where else "")
        sql += " ORDER BY created DESC"
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        return [_rollout(row) for row in self._query(sql, params)]

    def get_rollout(self, rollout_id: str) -> RolloutRecord | None:
        """The rollout with this id, or None."""
        rows = self._query("SELECT * FROM rollouts WHERE id = ?", (rollout_id,))
        return _rollout(rows[0]) if rows else None

    def rollout_summary(self, checkpoint_id: str | None = None, eval_id: str | None = None) -> list[dict]:
        """Per (task, checkpoint): count, successes, success rate, failures by stage, mean replans and
        planning time."""
        where, params = [], []
        if checkpoint_id is not None:
            where.append("checkpoint_id = ?")
            params.append(checkpoint_id)
        if eval_id is not None:
            where.append("eval_id = ?")
            params.append(eval_id)
        cond = (" WHERE " + " AND ".join(where)) if where else ""
        rows = self._query(
            "SELECT task, checkpoint_id, COUNT(*), SUM(success), AVG(replans), AVG(planning_time_s) "
            f"FROM rollouts{cond} GROUP BY task, checkpoint_id ORDER BY task, checkpoint_id",
            params,
        )
        stages = self._query(
            "SELECT task, checkpoint_id, failure_stage, COUNT(*) FROM rollouts"
            f"{cond}{' AND' if cond else ' WHERE'} success = 0 GROUP BY task, checkpoint_id, failure_stage",
            params,
        )
        by_stage: dict[tuple, dict] = {}
        for task, ck, stage, n in stages:
            by_stage.setdefault((task, ck), {})[stage or "unknown"] = n
        return [
            {
                "task": task,
                "checkpoint_id": ck,
                "rollouts": n,
                "successes": int(s or 0),
                "success_rate": (s or 0) / n,
                "failures_by_stage": by_stage.get((task, ck), {}),
                "mean_replans": replans,
                "mean_planning_time_s": plan_t,
            }
            for task, ck, n, s, replans, plan_t in rows
        ]

    # ------------------------------------------------------------------ helpers
    def _insert(self, table: str, d: dict) -> None:
        with self._lock:
            self._conn.execute(
                f"INSERT INTO {table}({', '.join(d)}) VALUES ({', '.join('?' * len(d))})", tuple(d.values())
            )
