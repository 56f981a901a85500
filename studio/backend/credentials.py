"""``studio bus credentials``: the keys, passwords and Zenoh configuration files of an authenticated, encrypted bus.

One run writes, under ``--out DIR``::

    ca/ca.pem ca/ca.key            the certificate authority (keep ca.key off the studio machines)
    hub/bus.json5                  the hub's config: TLS listener with client certificates required, the password
                                   dictionary and the access rules of every role
    hub/hub.pem hub.key ca.pem passwords.txt
    hub/embedded/sim.json5 train.json5 (+ their certificates)   for the workers ``studio serve`` starts itself
    sim/bus.json5 train/bus.json5 ui/bus.json5 (+ each role's certificate, key and ca.pem)

Every role connects over ``tls`` only, with its own client certificate (common name = the role) and its own random
password (user name = the role). The hub's access rules (Zenoh's ``access_control``) bind both to the role and allow
each role exactly the key expressions of :data:`GRANTS` — in both directions, since the hub is a router: what the
role may send (``ingress`` at the hub) and what the hub may pass to it (``egress``). Everything else is denied.
Private keys and the files holding passwords are mode 0600 and their directories 0700.

Paths inside a config file are relative to that file's directory (:class:`studio.backend.bus.BusConfig` resolves
them), so a role's directory can be copied anywhere. Certificates are made with the ``openssl`` command line.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from ipaddress import ip_address
from pathlib import Path
from typing import Any, Literal

from studio.backend import keys

Role = Literal["hub", "sim", "train", "ui"]
ROLES: tuple[Role, ...] = ("hub", "sim", "train", "ui")
#: Roles whose configs the hub's bundle also carries, for the workers ``studio serve`` / ``studio hub`` start.
EMBEDDED_ROLES: tuple[Role, ...] = ("sim", "train")
CONFIG_NAME = "bus.json5"
EMBEDDED_DIR = "embedded"
PASSWORDS_NAME = "passwords.txt"
CA_DAYS = 3650
CERT_DAYS = 825
DEFAULT_PORT = 7447

Flow = Literal["ingress", "egress"]


@dataclass(frozen=True)
class Grant:
    """Messages of some kinds on some key expressions, in one direction as the hub sees it: ``ingress`` is what the
    role sends to the hub, ``egress`` what the hub passes on to the role."""

    flow: Flow
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]
    #: ``deny`` carves an exception out of a wider allow (Zenoh: an explicit deny wins over any allow).
    permission: Literal["allow", "deny"] = "allow"


def _jobs(*leaves: str) -> tuple[str, ...]:
    return tuple(keys.all_jobs(leaf) for leaf in leaves)


def _sessions(*leaves: str) -> tuple[str, ...]:
    return tuple(f"{keys.ROOT}/sim/*/*/{leaf}" for leaf in leaves)


def _worker(kind: str, *leaves: str) -> tuple[str, ...]:
    return tuple(f"{keys.ROOT}/workers/{kind}/*/{leaf}" for leaf in leaves)


_UPLOADS = (keys.ALL_UPLOADS,)
#: Moving a job's files (:mod:`studio.backend.artifact_transfer`): every holder serves its files on
#: ``studio/blobs/<holder>/<content id>``, the hub takes offers and describes inputs on its two store keys.
_BLOBS = (f"{keys.ROOT}/blobs/*/*",)
_HUB_BLOBS = (f"{keys.ROOT}/blobs/hub/*",)
_HUB_STORE = (f"{keys.ROOT}/store/artifacts", f"{keys.ROOT}/store/inputs")
_HUB_INPUTS = (f"{keys.ROOT}/store/inputs",)
#: What a job's worker publishes about it (never ``submit``/``cancel``/``status``: those are the hub's).
_JOB_REPORTS = _jobs("report", "result", "progress", "artifacts", "poses")
_SESSION_OUTPUT = _sessions("poses", "frames", "status", "draft")


def _worker_grants(kind: str) -> list[Grant]:
    """A worker of ``kind``: announce itself under its kind, serve its queryables, report on jobs."""
    served = _worker(kind, *keys.WORKER_LEAVES)
    published = _worker(kind, "status") + _JOB_REPORTS
    return [
        Grant("ingress", ("liveliness_token",), (f"{keys.ROOT}/workers/{kind}/*",)),
        Grant("ingress", ("declare_queryable", "reply"), served),
        Grant("ingress", ("put",), published),
        Grant("egress", ("query",), served),
        Grant("egress", ("declare_subscriber",), published),
        Grant("ingress", ("query",), _BLOBS + _HUB_STORE),
        Grant("egress", ("declare_queryable", "reply"), _BLOBS + _HUB_STORE),
        Grant("ingress", ("declare_queryable", "reply"), _BLOBS),
        Grant("egress", ("query",), _BLOBS),
        # Only the hub serves the hub's files: no worker answers for it, nor is asked (even with a wildcard).
        Grant("ingress", ("declare_queryable", "reply"), _HUB_BLOBS, permission="deny"),
        Grant("egress", ("query",), _HUB_BLOBS, permission="deny"),
    ]


#: role -> what it may do. A UI submits, cancels and watches jobs, sees the workers, and drives teleop sessions
#: (which session is whose is the session's owner token, see :mod:`studio.backend.sim_worker`); a sim worker
#: announces itself, reports on jobs, hosts teleop sessions and ships episodes to the store; a trainer announces
#: itself and reports on jobs. The hub role (a second router joining this one) may do everything.
GRANTS: dict[Role, list[Grant]] = {
    "hub": [
        Grant(
            flow,
            (
                "put",
                "delete",
                "declare_subscriber",
                "query",
                "reply",
                "declare_queryable",
                "liveliness_token",
                "liveliness_query",
                "declare_liveliness_subscriber",
            ),
            (f"{keys.ROOT}/**",),
        )
        for flow in ("ingress", "egress")
    ],
    "sim": [
        *_worker_grants("sim"),
        Grant("ingress", ("declare_queryable", "reply"), _sessions("ctl")),
        Grant("ingress", ("put",), _SESSION_OUTPUT),
        Grant("ingress", ("declare_subscriber",), _sessions("cmd")),
        Grant("ingress", ("declare_liveliness_subscriber", "liveliness_query"), _sessions("client")),
        Grant("ingress", ("query",), _UPLOADS),
        Grant("egress", ("query",), _sessions("ctl")),
        Grant("egress", ("put",), _sessions("cmd")),
        Grant("egress", ("declare_subscriber",), _SESSION_OUTPUT),
        Grant("egress", ("liveliness_token",), _sessions("client")),
        Grant("egress", ("declare_queryable", "reply"), _UPLOADS),
    ],
    "train": _worker_grants("train"),
    "ui": [
        Grant("ingress", ("query",), _jobs("submit", "cancel", "status", "result", "progress")),
        Grant(
            "egress",
            ("declare_queryable", "reply"),
            _jobs("submit", "cancel", "status", "result", "progress"),
        ),
        Grant(
            "ingress", ("declare_subscriber",), _jobs("status", "progress", "artifacts", "result", "poses")
        ),
        Grant("egress", ("put",), _jobs("status", "progress", "artifacts", "result", "poses")),
        Grant("ingress", ("declare_liveliness_subscriber", "liveliness_query"), (keys.ALL_WORKER_TOKENS,)),
        Grant("egress", ("liveliness_token",), (keys.ALL_WORKER_TOKENS,)),
        Grant("ingress", ("declare_subscriber", "query"), (keys.ALL_WORKER_STATUS,)),
        Grant("egress", ("put", "reply", "declare_queryable"), (keys.ALL_WORKER_STATUS,)),
        Grant("ingress", ("query",), _sessions("ctl")),
        Grant("egress", ("declare_queryable", "reply"), _sessions("ctl")),
        Grant("ingress", ("put",), _sessions("cmd")),
        Grant("egress", ("declare_subscriber",), _sessions("cmd")),
        Grant("ingress", ("liveliness_token",), _sessions("client")),
        Grant("ingress", ("declare_subscriber",), _SESSION_OUTPUT),
        Grant("egress", ("put",), _SESSION_OUTPUT),
        # Have the hub describe a submitted job's inputs by content id, for workers with their own data dir.
        Grant("ingress", ("query",), _HUB_INPUTS),
        Grant("egress", ("declare_queryable", "reply"), _HUB_INPUTS),
    ],
}


class CredentialsError(RuntimeError):
    """Credentials could not be written (openssl missing or failing, files in the way)."""


def access_control() -> dict[str, Any]:
    """The hub's ``access_control`` section: deny by default, each role's :data:`GRANTS` for its subject (certificate
    common name *and* user name both the role)."""
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        ids = []
        for n, grant in enumerate(GRANTS[role]):
            rule_id = f"{role}-{n}"
            ids.append(rule_id)
            rules.append(
                {
                    "id": rule_id,
                    "permission": grant.permission,
                    "flows": [grant.flow],
                    "messages": list(grant.messages),
                    "key_exprs": list(grant.key_exprs),
                }
            )
        policies.append({"id": f"{role}-policy", "rules": ids, "subjects": [role]})
    subjects = [{"id": role, "cert_common_names": [role], "usernames": [role]} for role in ROLES]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# ---------------------------------------------------------------------------------------------- certificates
def _openssl(*args: str) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CredentialsError(
            "the `openssl` command is needed to make certificates (apt-get install openssl)"
        )
    done = subprocess.run([exe, *args], capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        why = (done.stderr.strip().splitlines() or ["no message"])[0]
        raise CredentialsError(f"openssl {args[0]} failed: {why}")


def _private_key(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path))
    path.chmod(0o600)


def make_ca(directory: Path) -> tuple[Path, Path]:
    """A self-signed certificate authority: (certificate, key)."""
    cert, key = directory / "ca.pem", directory / "ca.key"
    _private_key(key)
    with tempfile.TemporaryDirectory(prefix="studio-ca-") as tmp:
        conf = Path(tmp) / "ca.cnf"
        conf.write_text(
            "[req]\ndistinguished_name = dn\nprompt = no\nx509_extensions = ca\n"
            "[dn]\nCN = osvi-studio-bus-ca\n"
            "[ca]\nbasicConstraints = critical,CA:TRUE\nkeyUsage = critical,keyCertSign,cRLSign\n"
            "subjectKeyIdentifier = hash\n"
        )
        _openssl(
            "req",
            "-x509",
            "-new",
            "-key",
            str(key),
            "-config",
            str(conf),
            "-days",
            str(CA_DAYS),
            "-out",
            str(cert),
        )
    return cert, key


def _san(hosts: Iterable[str]) -> str:
    names = []
    for host in hosts:
        try:
            names.append(f"IP:{ip_address(host)}")
        except ValueError:
            names.append(f"DNS:{host}")
    return ",".join(dict.fromkeys(names))


def make_certificate(
    ca: tuple[Path, Path], directory: Path, name: str, *, server_hosts: Sequence[str] = ()
) -> tuple[Path, Path]:
    """A certificate signed by ``ca`` with common name ``name``: a client certificate, and also a server one for
    ``server_hosts`` (its subject alternative names) when given. Returns (certificate, key)."""
    cert, key = directory / f"{name}.pem", directory / f"{name}.key"
    _private_key(key)
    usage = "serverAuth,clientAuth" if server_hosts else "clientAuth"
    extensions = [
        "basicConstraints = critical,CA:FALSE",
        "keyUsage = critical,digitalSignature",
        f"extendedKeyUsage = {usage}",
        "subjectKeyIdentifier = hash",
        "authorityKeyIdentifier = keyid",
    ]
    if server_hosts:
        extensions.append(f"subjectAltName = {_san(server_hosts)}")
    with tempfile.TemporaryDirectory(prefix="studio-cert-") as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        ext.write_text("[leaf]\n" + "\n".join(extensions) + "\n")
        _openssl("req", "-new", "-key", str(key), "-subj", f"/CN={name}", "-out", str(csr))
        _openssl(
            "x509",
            "-req",
            "-in",
            str(csr),
            "-CA",
            str(ca[0]),
            "-CAkey",
            str(ca[1]),
            "-set_serial",
            f"0x{secrets.token_hex(16)}",
            "-days",
            str(CERT_DAYS),
            "-extfile",
            str(ext),
            "-extensions",
            "leaf",
            "-out",
            str(cert),
        )
    return cert, key


# ---------------------------------------------------------------------------------------------- configs
def _tls(role: str, *, listen: bool, ca: str = "ca.pem") -> dict[str, Any]:
    tls: dict[str, Any] = {
        "root_ca_certificate": ca,
        "enable_mtls": True,  # a client sends its certificate only with this set; a listener then requires one
        "connect_certificate": f"{role}.pem",
        "connect_private_key": f"{role}.key",
    }
    if listen:
        tls.update(listen_certificate=f"{role}.pem", listen_private_key=f"{role}.key")
    return tls


def hub_config(listen: str, password: str) -> dict[str, Any]:
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "transport": {
            "link": {"protocols": ["tls"], "tls": _tls("hub", listen=True)},
            "auth": {"usrpwd": {"user": "hub", "password": password, "dictionary_file": PASSWORDS_NAME}},
        },
        "access_control": access_control(),
    }


def client_config(role: Role, connect: str, password: str) -> dict[str, Any]:
    return {
        "mode": "client",
        "connect": {"endpoints": [connect]},
        "transport": {
            "link": {"protocols": ["tls"], "tls": _tls(role, listen=False)},
            "auth": {"usrpwd": {"user": role, "password": password}},
        },
    }


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    path.chmod(0o600)


def _write_config(path: Path, role: str, config: dict[str, Any]) -> None:
    header = (
        f"// Zenoh configuration of the studio's {role} role, made by `studio bus credentials`.\n"
        "// Paths are relative to this file's directory. It holds a password: keep it private (mode 0600).\n"
    )
    _write_private(path, header + json.dumps(config, indent=2) + "\n")


def _private_dir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    path.chmod(0o700)
    return path


def _endpoint_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


@dataclass(frozen=True)
class Bundle:
    """What :func:`generate` wrote: each role's config file."""

    out: Path
    configs: dict[str, Path]


def generate(
    out: str | os.PathLike,
    hosts: Sequence[str],
    *,
    port: int = DEFAULT_PORT,
    listen_host: str = "0.0.0.0",
    force: bool = False,
) -> Bundle:
    """Write a CA, certificates, passwords and one config per role under ``out`` (see the module docstring).

    ``hosts`` are the names and addresses workers use to reach the hub (the first one goes into the workers'
    configs); ``localhost`` and ``127.0.0.1`` are always in the hub's certificate.
    """
    out = Path(out)
    hosts = [h.strip() for h in hosts if h.strip()]
    if not hosts:
        raise CredentialsError("give at least one --host: the hub's name or address as workers reach it")
    if not 0 < port < 65536:
        raise CredentialsError(f"--port must be within 1..65535, got {port}")
    existing = [out / d for d in ("ca", *ROLES) if (out / d).exists()]
    if existing and not force:
        raise CredentialsError(f"{existing[0]} exists; pass --force to replace the credentials in {out}")
    for d in existing:
        shutil.rmtree(d)
    _private_dir(out)
    ca = make_ca(_private_dir(out / "ca"))
    passwords = {role: secrets.token_urlsafe(24) for role in ROLES}
    server_hosts = [*hosts, "localhost", "127.0.0.1"]
    connect = f"tls/{_endpoint_host(hosts[0])}:{port}"
    configs: dict[str, Path] = {}

    def role_dir(directory: Path, role: Role, *, server: bool = False) -> None:
        make_certificate(ca, directory, role, server_hosts=server_hosts if server else ())
        shutil.copyfile(ca[0], directory / "ca.pem")

    hub_dir = _private_dir(out / "hub")
    role_dir(hub_dir, "hub", server=True)
    _write_private(hub_dir / PASSWORDS_NAME, "".join(f"{r}:{passwords[r]}\n" for r in ROLES))
    configs["hub"] = hub_dir / CONFIG_NAME
    _write_config(
        configs["hub"], "hub", hub_config(f"tls/{_endpoint_host(listen_host)}:{port}", passwords["hub"])
    )
    embedded = _private_dir(hub_dir / EMBEDDED_DIR)
    for role in EMBEDDED_ROLES:
        role_dir(embedded, role)
        local = client_config(role, f"tls/127.0.0.1:{port}", passwords[role])
        _write_config(embedded / f"{role}.json5", f"{role} (embedded)", local)
    for role in ROLES:
        if role == "hub":
            continue
        directory = _private_dir(out / role)
        role_dir(directory, role)
        configs[role] = directory / CONFIG_NAME
        _write_config(configs[role], role, client_config(role, connect, passwords[role]))
    return Bundle(out=out, configs=configs)


# ---------------------------------------------------------------------------------------------- command
#: How each role's process starts with its config (``studio serve`` or ``studio hub`` for the hub).
START_COMMANDS: dict[str, str] = {
    "hub": "studio serve --bus-config {config}",
    "sim": "studio worker sim --bus-config {config}",
    "train": "studio worker train --bus-config {config} --data-dir DIR",
    "ui": "a client session: BusConfig.from_file('{config}')",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser(
        "credentials",
        help="write a CA, certificates, passwords and a Zenoh config per role (hub, sim, train, ui)",
        description=__doc__.splitlines()[0],
    )
    p.add_argument("--out", required=True, help="directory to write into (one subdirectory per role)")
    p.add_argument(
        "--host",
        action="append",
        default=[],
        required=True,
        help="a name or address workers use to reach the hub (repeatable; the first goes into their configs)",
    )
    p.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"the hub's TLS port (default {DEFAULT_PORT})"
    )
    p.add_argument(
        "--listen-host",
        default="0.0.0.0",
        help="the interface the hub listens on (default 0.0.0.0: every interface; TLS and passwords guard it)",
    )
    p.add_argument("--force", action="store_true", help="replace credentials already in --out")


def run(args: argparse.Namespace) -> int:
    try:
        bundle = generate(args.out, args.host, port=args.port, listen_host=args.listen_host, force=args.force)
    except CredentialsError as e:
        print(f"studio bus credentials: {e}", file=sys.stderr)
        return 1
    print(f"wrote the bus credentials to {bundle.out}; keep {bundle.out / 'ca'} off the studio machines.")
    print("Copy each role's directory to its machine, then start (paths as copied):")
    for role, path in bundle.configs.items():
        print(f"  {role:5s} {path.parent}/  ->  {START_COMMANDS[role].format(config=f'{role}/{path.name}')}")
    return 0
