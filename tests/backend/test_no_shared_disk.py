"""The studio on three "machines" that share no disk: a hub, a trainer and a sim worker as separate processes, each
with its own data directory, on the bus only. A tiny model is trained on the hub's episodes, then plans and rolls out
on the sim worker, and a scripted and a teleop recording land in the hub's store; every file arrives by content id,
byte for byte.

:func:`run_flow` is the whole scenario; the second test runs it again with the hub, the trainer and the sim worker each
in its own network namespace (veth pairs to the hub's) over the authenticated bus (``studio bus credentials``: TLS,
a password and access rules per role), and checks that a client without credentials is refused at connect; it is
skipped where namespaces cannot be made (not root, no CAP_NET_ADMIN)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import secrets
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.artifact_transfer import ArtifactJobClient
from studio.backend.presence import Directory
from studio.backend.teleop_client import TeleopClient
from studio.data.store import EpisodeStore

from .conftest import HERE, wait_worker
from .test_train_job_small_data import GREEN, RED, TINY

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "data"))
from data_fixtures import make_recording

pytestmark = pytest.mark.timeout(900)  # 15-25 s on a quiet 2-core machine; generous for a loaded one


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class Process:
    """A ``studio`` process (optionally under a command prefix such as ``ip netns exec NS``) whose output is kept."""

    def __init__(self, args: Sequence[str], log: Path, prefix: Sequence[str] = ()):
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]),
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
        }
        self.log = log
        with open(log, "ab") as out:
            self.proc = subprocess.Popen(
                [*prefix, sys.executable, "-m", "studio.cli", *args],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
            )

    def text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def wait_for(self, line: str, timeout: float) -> None:
        done = threading.Event()
        deadline = threading.Timer(timeout, done.set)
        deadline.start()
        try:
            while not done.wait(0.1):
                if line in self.text():
                    return
                if self.proc.poll() is not None:
                    break
        finally:
            deadline.cancel()
        raise AssertionError(f"no {line!r} from {self.log.name}:\n{self.text()}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def seed_hub_store(hub_dir: Path) -> str:
    """Training pairs (cube->red: one demonstration, two agent episodes; a failed cube->green demonstration) and
    the demonstration the plan and the rollout imitate; returns its id."""
    with EpisodeStore(hub_dir) as store:
        demo = store.add_episode(
            make_recording(task=RED, robot="sawyer", seed=0), role="expert", source="teleop"
        )
        for seed in (1, 2):
            store.add_episode(
                make_recording(task=RED, robot="panda", seed=seed), role="agent", source="teleop"
            )
        failed = make_recording(task=GREEN, robot="sawyer", seed=3, success=False)
        store.add_episode(failed, role="expert", source="teleop")
    return demo.id


def run_flow(
    tmp_path: Path,
    *,
    hub_listen: str,
    connect: Mapping[str, str],
    prefixes: Mapping[str, Sequence[str]],
    bus_configs: Mapping[str, Path] | None = None,
) -> None:
    """Hub, trainer and sim worker with their own data dirs; train, plan, roll out and record; check every file.

    ``connect`` is where the ``trainer``, the ``sim`` worker and this test's ``client`` find the hub; ``prefixes``
    the command each process runs under (by name: ``hub``, ``trainer``, ``sim``); ``bus_configs`` the role config
    (``studio bus credentials``) of each of them and of the ``client``, for an authenticated bus."""
    dirs = {name: tmp_path / name for name in ("hub", "trainer", "sim")}
    for d in dirs.values():
        d.mkdir()
    demo = seed_hub_store(dirs["hub"])

    def config_args(name: str) -> list[str]:
        return [] if bus_configs is None else ["--bus-config", str(bus_configs[name])]

    procs: list[Process] = []
    session = None
    try:
        hub = Process(
            [
                "hub",
                "--listen",
                hub_listen,
                "--data-dir",
                str(dirs["hub"]),
                "--workers",
                "none",
                "--log-level",
                "WARNING",
                *config_args("hub"),
            ],
            tmp_path / "hub.log",
            prefixes.get("hub", ()),
        )
        procs.append(hub)
        hub.wait_for("studio hub ready", 60)
        for kind, name in (("train", "trainer"), ("sim", "sim")):
            procs.append(
                Process(
                    [
                        "worker",
                        kind,
                        "--connect",
                        connect[name],
                        "--id",
                        f"{name}-1",
                        "--data-dir",
                        str(dirs[name]),
                        "--own-data-dir",
                        "--log-level",
                        "WARNING",
                        *config_args(name),
                    ],
                    tmp_path / f"{name}.log",
                    prefixes.get(name, ()),
                )
            )
        if bus_configs is None:  # the UI's side, as another client
            client_config = bus.BusConfig.worker([connect["client"]])
        else:
            client_config = bus.BusConfig.from_file(bus_configs["client"], connect=[connect["client"]])
        session = bus.open_session(client_config)
        directory = Directory(session)
        wait_worker(directory, "trainer-1")
        wait_worker(directory, "sim-1")
        jobs = ArtifactJobClient(session)  # asks the hub to describe each job's inputs by content id

        def logs() -> str:
            return "\n".join(p.text() for p in procs)

        def finish(kind: str, spec: dict, timeout: float) -> dict:
            status = jobs.submit(kind, spec)
            assert ("inputs" in jobs.status(status.job).spec) == (kind != "expert")  # it reads no file
            with jobs.watch(status.job) as watch:
                end = watch.wait(timeout=timeout)
            assert end is not None and end.state == "succeeded", f"{kind}: {end}\n{logs()}"
            result = jobs.result(status.job)
            assert result is not None
            return result.result

        # Train, as the Train panel submits it: paths in the hub's data dir, the split file in the run dir.
        run_rel = Path("runs") / "train-tiny"
        hub_run = dirs["hub"] / run_rel
        hub_run.mkdir(parents=True)
        (hub_run / "split.json").write_text(
            json.dumps({"scene": "pick_place", "train": [RED, GREEN], "test": [], "val_fraction": 0.0})
        )
        trained = finish(
            "train",
            {
                "data_dir": str(dirs["hub"]),
                "run_dir": str(hub_run),
                "config": "cpu",
                "overrides": TINY,
                "steps": 2,
                "seed": 0,
                "scene": str(hub_run / "split.json"),
                "threads": 1,
            },
            400,
        )
        assert trained["run_dir"] == str(hub_run.resolve())  # the run is told as the hub's
        with EpisodeStore(dirs["hub"]) as hub_store, EpisodeStore(dirs["trainer"]) as trainer_store:
            assert {m.id for m in trainer_store.episodes()} == {m.id for m in hub_store.episodes()}
            for meta in hub_store.episodes():  # the training data arrived byte for byte
                for name in ("meta.json", "frames.mp4", "arrays.npz"):
                    assert sha256(trainer_store.episode_dir(meta.id) / name) == sha256(
                        hub_store.episode_dir(meta.id) / name
                    )
        for name in ("last.pt", "metrics.jsonl", "config.json"):
            theirs = dirs["trainer"] / run_rel / name
            assert sha256(hub_run / name) == sha256(theirs), name
        checkpoint_id = sha256(hub_run / "last.pt")
        assert (dirs["hub"] / "artifacts" / "blobs" / checkpoint_id).is_file()  # received by content id

        # Plan and roll out with the trained checkpoint on the sim worker.
        spec = {"checkpoint": str(hub_run / "last.pt"), "expert_episode_id": demo, "task": RED, "seed": 1}
        planned = finish("plan", spec, 300)
        assert sha256(dirs["sim"] / run_rel / "last.pt") == checkpoint_id  # fetched by content id
        plan_rel = Path(planned["path"])
        assert sha256(dirs["hub"] / plan_rel) == sha256(dirs["sim"] / plan_rel)
        with np.load(dirs["hub"] / plan_rel, allow_pickle=False) as plan:
            assert plan["waypoints_world"].shape == (5, 4)

        rolled = finish("rollout", {**spec, "replans": 0, "speed": 0.0}, 300)
        with EpisodeStore(dirs["hub"]) as hub_store, EpisodeStore(dirs["sim"]) as sim_store:
            record = hub_store.catalog.get_rollout(rolled["rollout_id"])
            assert record is not None and record.episode_id == rolled["episode_id"]
            assert record.path == str((dirs["hub"] / "rollouts" / rolled["rollout_id"]).resolve())
            for name in ("meta.json", "frames.mp4", "arrays.npz"):
                ours = sim_store.episode_dir(record.episode_id) / name
                assert sha256(hub_store.episode_dir(record.episode_id) / name) == sha256(ours)
            for f in (dirs["sim"] / "rollouts" / record.id).iterdir():
                assert sha256(Path(record.path) / f.name) == sha256(f)

        # A scripted demonstration stored by the sim worker is added to the hub's store byte for byte.
        scripted = finish("expert", {"task": RED, "seed": 5, "robot": "sawyer"}, 300)
        with EpisodeStore(dirs["hub"]) as hub_store, EpisodeStore(dirs["sim"]) as sim_store:
            assert hub_store.get(scripted["episode_id"]).source == "scripted"
            for name in ("meta.json", "frames.mp4", "arrays.npz"):
                ours = sim_store.episode_dir(scripted["episode_id"]) / name
                assert sha256(hub_store.episode_dir(scripted["episode_id"]) / name) == sha256(ours)

        # A teleop recording on the sim worker lands in the hub's store, not the worker's.
        with TeleopClient(session, "sim-1") as client:
            client.open("pick_place", "sawyer", RED, seed=2)
            client.start_recording()
            start = np.asarray(client.poses.wait_until(lambda f: True, 10.0).ee_pos)
            for _ in range(40):  # well over the shortest recording the store takes
                assert client.wait_ack(client.set_target(start + np.array([0.0, 0.0, 0.05]), 0.0)) is not None
            saved = client.stop_recording(timeout=120)
        assert isinstance(saved, msg.EpisodeSaved) and saved.via == "bus", f"{saved}\n{logs()}"
        with EpisodeStore(dirs["hub"]) as hub_store, EpisodeStore(dirs["sim"]) as sim_store:
            assert hub_store.catalog.get_episode(saved.episode) is not None
            assert sim_store.catalog.get_episode(saved.episode) is None
        if bus_configs is not None:  # a client without credentials is refused at connect
            plain = bus.BusConfig.worker([connect["client"].replace("tls/", "tcp/", 1)])
            with pytest.raises(bus.BusError):
                bus.open_session(replace(plain, connect_timeout_s=3.0)).close()
        directory.close()
    finally:
        if session is not None:
            session.close()
        for p in reversed(procs):
            p.stop()


def test_train_plan_rollout_and_record_with_no_shared_disk(tmp_path):
    endpoint = bus.loopback_endpoint(bus.free_loopback_port())
    run_flow(
        tmp_path,
        hub_listen=endpoint,
        connect=dict.fromkeys(("trainer", "sim", "client"), endpoint),
        prefixes={},
    )


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


@contextlib.contextmanager
def namespaces() -> Iterator[dict[str, str]]:
    """A network namespace for the hub, the trainer and the sim worker; the hub's is joined by a veth pair to each of
    the others and to this test's (the UI's side). Yields each one's IP address of the hub by name (``client``,
    ``trainer``, ``sim``) and each namespace as ``ns:<role>``; every namespace (and with it its links) is deleted on
    the way out."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (CAP_NET_ADMIN); not root here")
    tag = secrets.token_hex(2)
    names = {role: f"osvi-{role[:3]}-{tag}" for role in ("hub", "trainer", "sim")}
    made: list[str] = []
    try:
        for ns in names.values():
            try:
                _ip("netns", "add", ns)
            except (subprocess.CalledProcessError, OSError) as e:
                pytest.skip(f"cannot create a network namespace here: {getattr(e, 'stderr', '') or e}")
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        hub_ns = names["hub"]
        addresses = {}
        for i, peer in enumerate(("client", "trainer", "sim"), start=1):
            near, far = f"vh{tag}{i}", f"vp{tag}{i}"  # the hub's end, the peer's end
            _ip("link", "add", near, "type", "veth", "peer", "name", far)
            _ip("link", "set", near, "netns", hub_ns)
            if peer != "client":
                _ip("link", "set", far, "netns", names[peer])
            _ip("-n", hub_ns, "addr", "add", f"10.77.{i}.1/30", "dev", near)
            _ip("-n", hub_ns, "link", "set", near, "up")
            where = [] if peer == "client" else ["-n", names[peer]]
            _ip(*where, "addr", "add", f"10.77.{i}.2/30", "dev", far)
            _ip(*where, "link", "set", far, "up")
            addresses[peer] = f"10.77.{i}.1"
        yield {**addresses, **{f"ns:{role}": ns for role, ns in names.items()}}
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        subprocess.run(["ip", "link", "del", f"vp{tag}1"], capture_output=True, timeout=30)


@pytest.mark.slow
def test_the_same_flow_with_each_process_in_its_own_network_namespace_over_the_authenticated_bus(tmp_path):
    with namespaces() as net:
        creds = tmp_path / "creds"
        hosts = [arg for peer in ("client", "trainer", "sim") for arg in ("--host", net[peer])]
        made = subprocess.run(
            [sys.executable, "-m", "studio.cli", "bus", "credentials", "--out", str(creds), *hosts],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert made.returncode == 0, made.stdout + made.stderr
        roles = {"hub": "hub", "trainer": "train", "sim": "sim", "client": "ui"}
        configs = {name: creds / role / "bus.json5" for name, role in roles.items()}
        prefixes = {role: ("ip", "netns", "exec", net[f"ns:{role}"]) for role in ("hub", "trainer", "sim")}
        connect = {peer: f"tls/{net[peer]}:7447" for peer in ("client", "trainer", "sim")}
        run_flow(
            tmp_path, hub_listen="tls/0.0.0.0:7447", connect=connect, prefixes=prefixes, bus_configs=configs
        )
