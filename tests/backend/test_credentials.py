"""`studio bus credentials` and the checks around it: what the files hold, who may read them, which rules the hub
gets, how a role config is read, and the refusal to listen beyond loopback without credentials."""

from __future__ import annotations

import argparse
import json
import logging
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from studio.backend import bus, credentials

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> credentials.Bundle:
    return credentials.generate(
        tmp_path_factory.mktemp("creds") / "out", ["studio-hub.lan", "10.0.0.5"], port=7500
    )


def read_config(path: Path) -> dict:
    text = path.read_text()
    return json.loads(text[text.index("{") :])  # after the comment header


def openssl(*args: str) -> str:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, check=True).stdout


def test_each_role_gets_a_certificate_of_its_own_signed_by_the_ca(bundle):
    out = bundle.out
    ca = out / "ca" / "ca.pem"
    for role in credentials.ROLES:
        cert = out / role / f"{role}.pem"
        assert openssl("verify", "-CAfile", str(ca), str(cert)).strip() == f"{cert}: OK"
        assert f"CN = {role}" in openssl("x509", "-in", str(cert), "-noout", "-subject")
        assert (out / role / "ca.pem").read_bytes() == ca.read_bytes()
    san = openssl("x509", "-in", str(out / "hub" / "hub.pem"), "-noout", "-ext", "subjectAltName")
    for name in ("DNS:studio-hub.lan", "IP Address:10.0.0.5", "DNS:localhost", "IP Address:127.0.0.1"):
        assert name in san
    usage = openssl(
        "x509", "-in", str(out / "ui" / "ui.pem"), "-noout", "-ext", "extendedKeyUsage,basicConstraints"
    )
    assert "TLS Web Client Authentication" in usage and "Server" not in usage and "CA:FALSE" in usage


def test_secrets_are_private_and_each_role_has_its_own_password(bundle):
    out = bundle.out
    private = [out / "ca" / "ca.key", out / "hub" / credentials.PASSWORDS_NAME]
    private += [out / r / f"{r}.key" for r in credentials.ROLES] + list(bundle.configs.values())
    private += sorted((out / "hub" / credentials.EMBEDDED_DIR).glob("*.json5"))
    for path in private:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    for directory in [out, out / "ca", *(out / r for r in credentials.ROLES)]:
        assert stat.S_IMODE(directory.stat().st_mode) == 0o700, directory

    dictionary = dict(
        line.split(":", 1) for line in (out / "hub" / credentials.PASSWORDS_NAME).read_text().splitlines()
    )
    assert sorted(dictionary) == sorted(credentials.ROLES)
    assert len(set(dictionary.values())) == len(credentials.ROLES)
    for role in ("sim", "train", "ui"):
        auth = read_config(bundle.configs[role])["transport"]["auth"]["usrpwd"]
        assert auth == {"user": role, "password": dictionary[role]}
    for role in credentials.EMBEDDED_ROLES:
        embedded = read_config(out / "hub" / credentials.EMBEDDED_DIR / f"{role}.json5")
        assert embedded["transport"]["auth"]["usrpwd"]["password"] == dictionary[role]
        assert embedded["connect"]["endpoints"] == ["tls/127.0.0.1:7500"]


def test_configs_are_tls_only_with_client_certificates(bundle):
    hub = read_config(bundle.configs["hub"])
    assert hub["mode"] == "router" and hub["listen"]["endpoints"] == ["tls/0.0.0.0:7500"]
    assert hub["transport"]["link"]["protocols"] == ["tls"]
    tls = hub["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True and tls["listen_certificate"] == "hub.pem"
    assert hub["transport"]["auth"]["usrpwd"]["dictionary_file"] == credentials.PASSWORDS_NAME
    for role in ("sim", "train", "ui"):
        conf = read_config(bundle.configs[role])
        assert conf["mode"] == "client" and conf["connect"]["endpoints"] == ["tls/studio-hub.lan:7500"]
        tls = conf["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True and tls["connect_certificate"] == f"{role}.pem"
        assert "access_control" not in conf


def test_access_rules_deny_by_default_and_bind_each_role_to_its_certificate_and_user(bundle):
    acl = read_config(bundle.configs["hub"])["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: (s["cert_common_names"], s["usernames"]) for s in acl["subjects"]} == {
        r: ([r], [r]) for r in credentials.ROLES
    }
    rules = {r["id"]: r for r in acl["rules"]}
    by_role = {p["subjects"][0]: [rules[i] for i in p["rules"]] for p in acl["policies"]}

    def allowed(role: str, flow: str, message: str) -> set[str]:
        return {
            k
            for r in by_role[role]
            if r["permission"] == "allow" and flow in r["flows"] and message in r["messages"]
            for k in r["key_exprs"]
        }

    assert "studio/jobs/*/submit" in allowed("ui", "ingress", "query")
    for worker in ("sim", "train"):
        assert "studio/jobs/*/submit" not in allowed(worker, "ingress", "query")
        assert "studio/jobs/*/report" in allowed(worker, "ingress", "put")
        assert f"studio/workers/{worker}/*" in allowed(worker, "ingress", "liveliness_token")
    assert not any("report" in k for k in allowed("ui", "ingress", "put"))
    assert allowed("ui", "ingress", "put") == {"studio/sim/*/*/cmd"}
    assert "studio/sim/*/*/ctl" in allowed("sim", "ingress", "declare_queryable")
    assert not any(k.startswith("studio/sim/") for k in allowed("train", "ingress", "declare_queryable"))
    assert not allowed("ui", "ingress", "declare_queryable")
    # Nobody but the hub receives teleop commands (their attachment is a session's owner token).
    assert "studio/sim/*/*/cmd" not in allowed("ui", "egress", "put")


def test_existing_credentials_are_kept_unless_forced(bundle):
    with pytest.raises(credentials.CredentialsError, match="--force"):
        credentials.generate(bundle.out, ["studio-hub.lan"])
    with pytest.raises(credentials.CredentialsError, match="--host"):
        credentials.generate(bundle.out.parent / "other", [" "])


def test_a_role_config_is_read_with_its_paths_from_its_directory(bundle):
    cfg = bus.BusConfig.from_file(bundle.configs["ui"])
    assert cfg.mode == "client" and cfg.connect == ("tls/studio-hub.lan:7500",) and cfg.listen == ()
    z = cfg.zenoh_config()
    assert json.loads(z.get_json("transport/link/tls/connect_certificate")) == str(
        bundle.out / "ui" / "ui.pem"
    )
    assert json.loads(z.get_json("transport/link/tls/root_ca_certificate")) == str(
        bundle.out / "ui" / "ca.pem"
    )
    assert json.loads(z.get_json("transport/auth/usrpwd/user")) == "ui"
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    assert json.loads(z.get_json("transport/link/tx/lease")) == bus.LEASE_MS

    p = argparse.ArgumentParser()
    bus.add_bus_arguments(p, "worker")
    args = p.parse_args(["--bus-config", str(bundle.configs["sim"]), "--connect", "tls/127.0.0.1:7600"])
    worker = bus.bus_config_from_args(args, "worker")
    assert worker.connect == ("tls/127.0.0.1:7600",) and worker.config_file == str(bundle.configs["sim"])
    assert bus.bus_config_from_args(p.parse_args(worker.to_args()), "worker") == worker

    security = bus.BusConfig.from_file(bundle.configs["hub"]).security()
    assert security is not None and security.guards_listening and security.protocols == ("tls",)
    with pytest.raises(ValueError, match="cannot read the bus config"):
        bus.BusConfig.from_file(bundle.out / "missing.json5")


def test_listening_beyond_loopback_needs_tls_passwords_and_rules(bundle, tmp_path):
    assert bus.BusConfig.hub().listen_problem() is None  # loopback: as before
    plain = bus.BusConfig.hub(["tcp/0.0.0.0:7447"])
    assert "refusing to listen on tcp/0.0.0.0:7447" in plain.listen_problem()
    with pytest.raises(bus.BusError, match="--insecure-listen-without-auth"):
        bus.open_session(plain)  # refused before anything binds
    secured = bus.BusConfig.from_file(bundle.configs["hub"])
    assert secured.listen == ("tls/0.0.0.0:7500",) and secured.listen_problem() is None
    tcp_beside = bus.BusConfig.from_file(
        bundle.configs["hub"], listen=["tls/0.0.0.0:7500", "tcp/10.0.0.5:7447"]
    )
    assert "tcp/10.0.0.5:7447 is not TLS" in tcp_beside.listen_problem()

    unruled = read_config(bundle.configs["hub"])
    del unruled["access_control"]
    unruled["transport"]["auth"]["usrpwd"].pop("dictionary_file")
    path = bundle.configs["hub"].with_name("unruled.json5")
    path.write_text(json.dumps(unruled))
    problem = bus.BusConfig.from_file(path).listen_problem()
    assert "lacks a password dictionary, access rules denying by default" in problem


def test_the_insecure_flag_lets_the_hub_try_and_says_so(caplog):
    """With the flag the refusal is lifted (the address here is not this machine's, so Zenoh itself fails to bind:
    nothing listens) and a warning names the risk."""
    cfg = bus.BusConfig(mode="router", listen=("tcp/192.0.2.1:7447",), insecure_listen=True)
    with caplog.at_level(logging.WARNING, logger="studio.backend"), pytest.raises(bus.BusError) as refused:
        bus.open_session(cfg)
    assert "refusing" not in str(refused.value) and "cannot open the bus as router" in str(refused.value)
    assert any(
        "INSECURE" in r.getMessage() and "tcp/192.0.2.1:7447" in r.getMessage() for r in caplog.records
    )
    assert bus.local_endpoint("tls/0.0.0.0:7447") == "tls/127.0.0.1:7447"
    assert bus.local_endpoint("tcp/[::]:7447") == "tcp/127.0.0.1:7447"
    assert bus.local_endpoint("tls/10.0.0.5:7447") == "tls/10.0.0.5:7447"


def test_studio_hub_refuses_an_unguarded_listen_in_one_line(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "hub",
            "--listen",
            "tcp/0.0.0.0:7447",
            "--workers",
            "none",
            "--data-dir",
            str(tmp_path / "data"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    lines = [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]
    assert out.returncode == 1 and len(lines) == 1, lines
    assert (
        lines[0].startswith("studio hub: refusing to listen on tcp/0.0.0.0:7447")
        and "studio bus credentials" in lines[0]
    )


def test_the_command_writes_a_bundle_and_says_how_to_start_each_role(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "bus",
            "credentials",
            "--out",
            str(tmp_path / "creds"),
            "--host",
            "studio-hub.lan",
            "--port",
            "7600",
        ],
        capture_output=True,
        text=True,
        timeout=90,
        stdin=subprocess.DEVNULL,
    )
    assert out.returncode == 0, out.stderr
    assert "studio worker sim --bus-config sim/bus.json5" in out.stdout
    assert read_config(tmp_path / "creds" / "sim" / "bus.json5")["connect"]["endpoints"] == [
        "tls/studio-hub.lan:7600"
    ]
    again = subprocess.run(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "bus",
            "credentials",
            "--out",
            str(tmp_path / "creds"),
            "--host",
            "x",
        ],
        capture_output=True,
        text=True,
        timeout=90,
        stdin=subprocess.DEVNULL,
    )
    assert again.returncode == 1 and again.stderr.count("\n") == 1 and "--force" in again.stderr
