"""The bus with credentials from `studio bus credentials`, on loopback TLS: who gets in, and what each role may do.

One set of credentials is made per module; the hub listens on ``tls/127.0.0.1:<free port>``. A client without the
right certificate and password is refused when it connects; a client with credentials of another role is let in,
but the hub's access rules drop what that role may not send — the hub never sees it.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh

from studio.backend import bus, credentials, keys
from studio.backend import messages as msg
from studio.backend.embedded import start_embedded_workers
from studio.backend.hub import Hub
from studio.backend.job_client import JobClient
from studio.backend.presence import Directory
from studio.backend.teleop_client import TeleopClient

from .conftest import Workers, wait_worker

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> credentials.Bundle:
    return credentials.generate(
        tmp_path_factory.mktemp("creds"), ["localhost"], port=bus.free_loopback_port()
    )


@pytest.fixture
def tls_endpoint() -> str:
    return f"tls/127.0.0.1:{bus.free_loopback_port()}"


@pytest.fixture
def hub(bundle, tls_endpoint, tmp_path):
    h = Hub(bus.BusConfig.from_file(bundle.configs["hub"], listen=[tls_endpoint]), data_dir=tmp_path / "data")
    yield h
    h.close()


def role_config(bundle, role: str, endpoint: str, timeout: float = 10.0, **changes) -> bus.BusConfig:
    """A role's client config connecting to ``endpoint``, giving up after ``timeout`` s; ``changes`` edit its file
    (a copy) first."""
    path = Path(bundle.configs[role])
    if changes:
        text = path.read_text()
        config = json.loads(text[text.index("{") :])
        for dotted, value in changes.items():
            *parents, leaf = dotted.split(".")
            node = config
            for p in parents:
                node = node[p]
            if value is None:
                node.pop(leaf, None)
            else:
                node[leaf] = value
        path = path.with_name(f"edited-{len(changes)}-{'-'.join(sorted(changes))}.json5")
        path.write_text(json.dumps(config))
    return replace(bus.BusConfig.from_file(path, connect=[endpoint]), connect_timeout_s=timeout)


@pytest.fixture
def open_role(bundle, tls_endpoint):
    sessions: list[zenoh.Session] = []

    def open_(role: str, timeout: float = 10.0, **changes) -> zenoh.Session:
        s = bus.open_session(role_config(bundle, role, tls_endpoint, timeout, **changes))
        sessions.append(s)
        return s

    yield open_
    for s in sessions:
        s.close()


def test_credentials_let_roles_in_and_a_ui_submit_a_job(hub, open_role):
    ui = open_role("ui")
    status = JobClient(ui).submit("count", {"steps": 1}, worker_kind="nobody")
    assert status.state == "queued"
    assert [j.job for j in hub.jobs.jobs()] == [status.job]
    assert [s.job for s in JobClient(ui).list()] == [status.job]


@pytest.mark.parametrize(
    "changes, what",
    [
        ({"transport.auth": None}, "no user or password"),
        ({"transport.auth.usrpwd.password": "not-the-password"}, "a wrong password"),
        (
            {"transport.link.tls.connect_certificate": None, "transport.link.tls.connect_private_key": None},
            "no client certificate",
        ),
        ({"transport.link.tls.enable_mtls": False}, "a certificate it does not present"),
    ],
)
def test_a_client_without_its_credentials_is_refused_at_connect(hub, open_role, changes, what):
    with pytest.raises(bus.BusError, match="cannot open the bus as client"):
        open_role("ui", timeout=3.0, **changes)


def test_a_plain_tcp_client_is_refused_at_connect(hub, tls_endpoint):
    plain = tls_endpoint.replace("tls/", "tcp/")
    with pytest.raises(bus.BusError, match="cannot open the bus as client"):
        bus.open_session(bus.BusConfig(mode="client", connect=(plain,), connect_timeout_s=3.0))


def test_a_ui_cannot_report_on_a_job_and_a_worker_cannot_submit_one(hub, open_role):
    seen: list[bytes] = []
    arrived = threading.Event()
    report_key = keys.job_key("job-1", "report")

    def on_report(sample: zenoh.Sample) -> None:
        seen.append(sample.payload.to_bytes())
        arrived.set()

    sub = hub.session.declare_subscriber(report_key, on_report)
    try:
        ui, sim = open_role("ui"), open_role("sim")
        time.sleep(0.5)  # both have the hub's subscriber declared to them
        ui.put(report_key, b"from the ui")
        sim.put(report_key, b"from the sim worker")  # the control: a worker may report
        assert arrived.wait(5.0)
        time.sleep(0.5)
        assert seen == [b"from the sim worker"]
    finally:
        sub.undeclare()

    for role in ("sim", "train"):
        with pytest.raises(bus.BusError, match="nobody answered"):
            JobClient(open_role(role), timeout=1.0).submit("count", {"steps": 1}, worker_kind="nobody")
    assert hub.jobs.jobs() == []


def test_a_ui_cannot_pose_as_a_worker(hub, open_role):
    """A queryable the UI declares on a worker's assign key is never asked: the hub's query finds nobody."""
    ui = open_role("ui")
    asked: list[str] = []
    q = ui.declare_queryable(keys.worker_key("sim", "fake", "assign"), lambda query: asked.append("x"))
    try:
        time.sleep(0.5)
        replies = list(hub.session.get(keys.worker_key("sim", "fake", "assign"), timeout=1.0))
        assert replies == [] and asked == []
    finally:
        q.undeclare()


def test_a_ui_never_sees_another_clients_teleop_commands(hub, open_role):
    """Teleop commands carry their session's owner token: only the sim role receives them, so a second UI client
    subscribing to every session's commands gets nothing, while a sim worker's subscriber (the control) gets them."""
    cmd_key = keys.session_key("sim-box", "s-1", "cmd")
    to_ui: list[bytes] = []
    to_sim: list[bytes] = []
    arrived = threading.Event()
    owner, other_ui, sim = open_role("ui"), open_role("ui"), open_role("sim")
    ui_sub = other_ui.declare_subscriber("studio/sim/*/*/cmd", lambda s: to_ui.append(s.payload.to_bytes()))
    sim_sub = sim.declare_subscriber(
        "studio/sim/*/*/cmd", lambda s: (to_sim.append(s.payload.to_bytes()), arrived.set())
    )
    try:
        time.sleep(0.5)
        owner.put(cmd_key, b"target", attachment=b"owner-token")
        assert arrived.wait(5.0)
        time.sleep(0.5)
        assert to_sim == [b"target"] and to_ui == []
    finally:
        ui_sub.undeclare()
        sim_sub.undeclare()


def test_no_worker_is_asked_for_the_hubs_files(hub, open_role):
    """A sim worker serving every holder's files (a wildcard) is asked for its own kind of key but never for the
    hub's: a fetcher of the hub's files only ever gets the hub's answer."""
    asked: list[str] = []

    def serve(query: zenoh.Query) -> None:
        asked.append(str(query.key_expr))
        query.reply(query.key_expr, b"forged")

    sim, trainer = open_role("sim"), open_role("train")
    q = sim.declare_queryable("studio/blobs/*/*", serve)
    try:
        time.sleep(0.5)
        hub_replies = list(trainer.get("studio/blobs/hub/" + "a" * 64, timeout=2.0))
        assert all(r.ok is None or r.ok.payload.to_bytes() != b"forged" for r in hub_replies)
        worker_replies = list(trainer.get("studio/blobs/sim-box/" + "a" * 64, timeout=2.0))
        assert [r.ok.payload.to_bytes() for r in worker_replies if r.ok is not None] == [b"forged"]
        assert asked == ["studio/blobs/sim-box/" + "a" * 64]
    finally:
        q.undeclare()


def test_mixed_credentials_get_in_but_may_do_nothing(hub, open_role, bundle):
    """The UI's certificate with the sim worker's password: neither role's rules match, so nothing passes."""
    sim_password = json.loads((text := Path(bundle.configs["sim"]).read_text())[text.index("{") :])[
        "transport"
    ]["auth"]["usrpwd"]["password"]
    mixed = open_role(
        "ui", **{"transport.auth.usrpwd.user": "sim", "transport.auth.usrpwd.password": sim_password}
    )
    with pytest.raises(bus.BusError, match="nobody answered"):
        JobClient(mixed, timeout=1.0).submit("count", {"steps": 1}, worker_kind="nobody")
    assert hub.jobs.jobs() == []


@pytest.mark.slow
def test_a_trainer_with_its_role_config_runs_a_job_over_tls(hub, bundle, tls_endpoint, open_role, tmp_path):
    workers = Workers(tls_endpoint, tmp_path)
    try:
        workers.start("train", "tls-trainer", "--bus-config", str(bundle.configs["train"]))
        ui = open_role("ui")
        directory = Directory(ui)
        try:
            wait_worker(directory, "tls-trainer", timeout=60)
        except AssertionError:
            raise AssertionError(workers.log("tls-trainer")) from None
        finally:
            directory.close()
        jobs = JobClient(ui)
        job = jobs.submit(
            "count", {"steps": 3, "step_s": 0.01, "run_dir": str(tmp_path / "run")}, worker_kind="train"
        )
        with jobs.watch(job.job) as watch:
            final = watch.wait(lambda w: w.result is not None and w.status.state == "succeeded", timeout=30)
            result = watch.result
        assert final is not None and final.state == "succeeded", workers.log("tls-trainer")
        assert isinstance(result, msg.JobResult) and result.result["counted"] == 3
    finally:
        workers.close()


@pytest.mark.slow
def test_the_hubs_own_trainer_joins_with_the_credentials_beside_the_hubs(hub, bundle):
    """`studio serve --bus-config hub/bus.json5` starts its trainer with ``hub/embedded/train.json5``."""
    expected = bundle.configs["hub"].parent / credentials.EMBEDDED_DIR / "train.json5"
    assert hub.embedded_worker_args("train") == ["--bus-config", str(expected)]
    assert hub.endpoint.startswith("tls/127.0.0.1:")
    with start_embedded_workers(hub, sim=0, train=1) as embedded:
        logs = [p.log_path for p in embedded.processes]
        assert embedded.wait_ready(hub.directory, timeout=90), "".join(
            p.read_text() for p in logs if p.exists()
        )


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_ui_drives_a_remote_sim_worker_whose_episode_is_shipped_over_tls(
    hub, bundle, tls_endpoint, open_role, tmp_path
):
    """Teleop from a `ui` client to a `sim` worker without a data dir: commands, poses, the recording's status and
    the episode's chunks all pass the hub's rules, and the episode lands in the hub's store."""
    workers = Workers(tls_endpoint, tmp_path)
    try:
        workers.start("sim", "tls-sim", "--bus-config", str(bundle.configs["sim"]), handlers=())
        ui = open_role("ui")
        directory = Directory(ui)
        try:
            wait_worker(directory, "tls-sim", timeout=90)
        except AssertionError:
            raise AssertionError(workers.log("tls-sim")) from None
        finally:
            directory.close()
        with TeleopClient(ui, "tls-sim", timeout=120.0) as client:
            client.open("pick_place", "sawyer", "pick_place/cube->red", seed=2)
            client.start_recording()
            start = np.asarray(client.poses.wait_until(lambda f: True, 10.0).ee_pos)
            for _ in range(25):
                assert client.wait_ack(client.set_target(start + np.array([0.0, 0.0, 0.05]), 0.0)) is not None
            saved = client.stop_recording(timeout=120)
        assert isinstance(saved, msg.EpisodeSaved) and saved.via == "bus", workers.log("tls-sim")
        assert hub.store.catalog.get_episode(saved.episode) is not None
    finally:
        workers.close()


def test_studio_hub_starts_with_its_role_config_and_lets_a_ui_in(bundle, tls_endpoint, open_role, tmp_path):
    hub = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "hub",
            "--bus-config",
            str(bundle.configs["hub"]),
            "--listen",
            tls_endpoint,
            "--workers",
            "none",
            "--data-dir",
            str(tmp_path / "data"),
            "--log-level",
            "WARNING",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert hub.stdout is not None
        ready = hub.stdout.readline()
        assert f"studio hub ready on {tls_endpoint}" in ready, ready + hub.stdout.read()
        ui = open_role("ui")
        status = JobClient(ui).submit("count", {"steps": 1}, worker_kind="nobody")
        assert [s.job for s in JobClient(ui).list()] == [status.job]
    finally:
        hub.send_signal(signal.SIGTERM)
        try:
            assert hub.wait(30) == 0
        finally:
            if hub.poll() is None:
                hub.kill()
