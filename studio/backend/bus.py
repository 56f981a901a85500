"""Zenoh session configuration and the typed request / reply / publish helpers the backend is built on.

Defaults keep the bus private to the machine: no multicast scouting, and every endpoint the studio
opens by itself is on ``127.0.0.1``. The UI host (the *hub*) runs a Zenoh router listening on
``tcp/127.0.0.1:7447``; workers are Zenoh clients connecting to it.

Going multi-machine means a *role config* per process (``--bus-config FILE``, written by ``studio bus
credentials``, see :mod:`studio.backend.credentials`): Zenoh's TLS with client certificates, a user and password
per role, and on the hub the access rules of every role. A process listening beyond loopback without them is
refused (:meth:`BusConfig.listen_problem`) unless ``--insecure-listen-without-auth`` says otherwise, loudly; see
``docs/deployment.md``.

Every payload goes through :mod:`studio.backend.messages`; the helpers here decode and validate what
arrives, answer malformed requests with an :class:`~studio.backend.messages.ErrorReply` and log and drop
malformed publications, so that no input can crash a process.
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any, Literal, TypeVar, overload

import zenoh

from studio.backend import messages as msg

log = logging.getLogger("studio.backend")

DEFAULT_PORT = 7447
DEFAULT_HUB_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
Mode = Literal["peer", "client", "router"]
MODES: tuple[Mode, ...] = ("peer", "client", "router")
#: Link protocols that encrypt and can authenticate the other side by certificate.
TLS_PROTOCOLS = ("tls", "quic")
INSECURE_FLAG = "--insecure-listen-without-auth"
#: Entries of a role config naming files; relative paths are taken from the config file's directory.
CONFIG_FILE_ENTRIES = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_certificate",
    "transport/link/tls/connect_private_key",
    "transport/auth/usrpwd/dictionary_file",
)

#: Zenoh's link lease: a peer that stops answering (machine gone, cable pulled) is declared lost after
#: this long, so its liveliness tokens vanish and its jobs are reported within the 5 s the studio promises.
#: A killed process is noticed at once (its TCP connection closes).
LEASE_MS = 3000

#: How a publication that must arrive is sent: an event (an episode stored), a job's report, artifact or result, a
#: journaled chunk, a worker's status. Zenoh's default drops a sample when the link's queue is full, which a loaded
#: machine reaches with a burst; these block until there is room instead (Zenoh closes a link that stays full for
#: 5 s, ``transport/link/tx/queue/congestion_control/block/wait_before_close``). Streams where the newest sample
#: supersedes the rest (poses, frames, progress, a session's periodic state, teleop commands, which the client
#: re-sends until applied) keep dropping, so a slow consumer never holds their producer back.
MUST_ARRIVE = zenoh.CongestionControl.BLOCK


class BusError(RuntimeError):
    """The bus could not be opened, or a request got no valid answer."""


class RequestTimeout(BusError):
    """A request was not answered within its timeout (Zenoh's own "Timeout" reply): the other side may be slow
    rather than absent, and may still act on the request."""


class RemoteError(BusError):
    """The other side answered a request with an :class:`~studio.backend.messages.ErrorReply`."""

    def __init__(self, code: str, message: str, key: str = ""):
        super().__init__(f"{code}: {message}" + (f" (from {key})" if key else ""))
        self.code = code
        self.message = message


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{int(port)}"


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint_in_use(endpoint: str) -> bool:
    """Whether a ``tcp/<host>:<port>`` endpoint of this machine is already listened on (another studio or hub);
    False for other protocols and for port 0."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit() or int(port) == 0:
        return False
    host = host.strip("[]") or "0.0.0.0"
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a closed listener's TIME_WAIT is no user
        try:
            s.bind((host, int(port)))
        except OSError as e:
            return e.errno == errno.EADDRINUSE  # any other failure is for Zenoh to report
    return False


def _check_endpoint(endpoint: str) -> str:
    proto, sep, address = endpoint.partition("/")
    if not sep or not proto or not address or ":" not in address:
        raise ValueError(
            f"endpoint {endpoint!r} must look like <protocol>/<host>:<port>, e.g. tcp/127.0.0.1:7447"
        )
    return endpoint


def is_loopback_endpoint(endpoint: str) -> bool:
    address = endpoint.partition("/")[2].split("#")[0]
    host = address.rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1") or host.startswith("127.")


def local_endpoint(endpoint: str) -> str:
    """The endpoint a process of this machine connects to for a listen endpoint: a wildcard host (``0.0.0.0``,
    ``[::]``) becomes ``127.0.0.1``, which the hub's certificate names too."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.split("#")[0].rpartition(":")
    if host.strip("[]") in ("0.0.0.0", "::", ""):
        return f"{proto}/127.0.0.1:{port}"
    return endpoint


def _json_entry(conf: zenoh.Config, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


@dataclass(frozen=True)
class BusSecurity:
    """What a role config file secures (read from the file; see :mod:`studio.backend.credentials`)."""

    listen_certificate: bool  # a TLS listener has a certificate and key
    client_certificates: bool  # enable_mtls: a listener requires, and a client presents, a certificate
    connect_certificate: bool  # a client certificate and key to present
    user: str  # the user name this process authenticates with ('' without)
    password_dictionary: bool  # a listener checks users against a password file
    access_control: bool  # access rules are enabled (deny by default)
    protocols: tuple[str, ...]  # the only link protocols allowed (empty: any)

    @property
    def guards_listening(self) -> bool:
        """TLS with client certificates, passwords and access rules on what it listens on."""
        return (
            self.listen_certificate
            and self.client_certificates
            and self.password_dictionary
            and self.access_control
        )

    @classmethod
    def of(cls, conf: zenoh.Config) -> BusSecurity:
        tls = _json_entry(conf, "transport/link/tls") or {}
        usrpwd = _json_entry(conf, "transport/auth/usrpwd") or {}
        acl = _json_entry(conf, "access_control") or {}
        return cls(
            listen_certificate=bool(tls.get("listen_certificate") and tls.get("listen_private_key")),
            client_certificates=bool(tls.get("enable_mtls")),
            connect_certificate=bool(tls.get("connect_certificate") and tls.get("connect_private_key")),
            user=str(usrpwd.get("user") or ""),
            password_dictionary=bool(usrpwd.get("dictionary_file")),
            access_control=bool(acl.get("enabled")) and acl.get("default_permission", "deny") == "deny",
            protocols=tuple(_json_entry(conf, "transport/link/protocols") or ()),
        )


def _read_config_file(path: str) -> zenoh.Config:
    """A role config file with its file entries made absolute (relative ones are from the file's directory)."""
    try:
        conf = zenoh.Config.from_file(path)
    except (zenoh.ZError, OSError) as e:
        raise ValueError(f"cannot read the bus config {path}: {one_line(e)}") from None
    base = os.path.dirname(os.path.abspath(path))
    for key in CONFIG_FILE_ENTRIES:
        value = _json_entry(conf, key)
        if isinstance(value, str) and value and not os.path.isabs(value):
            conf.insert_json5(key, json.dumps(os.path.join(base, value)))
    return conf


@dataclass(frozen=True)
class BusConfig:
    """How a process joins the bus.

    Attributes:
        mode: Zenoh mode: ``router`` (the hub), ``client`` (a worker connecting to a hub) or ``peer``.
        connect: endpoints to connect to.
        listen: endpoints to listen on (a peer without any listens on an OS-chosen loopback port).
        multicast_scouting: let Zenoh discover peers by UDP multicast (off: endpoints are explicit).
        lease_ms: link lease, see :data:`LEASE_MS`.
        connect_timeout_s: how long a client waits for its hub when opening before giving up.
        config_file: a role config (``--bus-config``): TLS, user and password, access rules; its mode and
            endpoints are the defaults of the ones above (see :meth:`from_file`).
        insecure_listen: listen beyond loopback even without TLS and authentication (logged as a warning).
    """

    mode: Mode = "client"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    lease_ms: int = LEASE_MS
    connect_timeout_s: float = 10.0
    config_file: str | None = None
    insecure_listen: bool = False

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"bus mode must be one of {MODES}, got {self.mode!r}")
        object.__setattr__(self, "connect", tuple(_check_endpoint(e) for e in self.connect))
        object.__setattr__(self, "listen", tuple(_check_endpoint(e) for e in self.listen))
        if self.mode == "client" and not self.connect:
            raise ValueError("a bus client needs at least one --connect endpoint")
        if self.mode == "client" and self.listen:
            raise ValueError("a bus client does not listen; use --mode peer to accept connections")
        if self.mode == "router" and not self.listen:
            raise ValueError("a bus router needs a --listen endpoint")

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike,
        *,
        mode: Mode | None = None,
        connect: Iterable[str] = (),
        listen: Iterable[str] = (),
        default_listen: Iterable[str] = (),
        default_connect: Iterable[str] = (),
    ) -> BusConfig:
        """A role config file, with ``mode`` / ``connect`` / ``listen`` (when given) in place of the file's; the
        defaults apply when neither names endpoints. Raises ValueError with one line for an unreadable file."""
        path = os.path.abspath(os.fspath(path))
        conf = _read_config_file(path)
        file_mode = _json_entry(conf, "mode")

        def endpoints(key: str) -> tuple[str, ...]:
            value = _json_entry(conf, key) or ()
            if isinstance(value, dict):  # Zenoh's per-mode form (its default when the file names none)
                value = value.get(file_mode, ()) or ()
            return tuple(value)

        file_connect, file_listen = endpoints("connect/endpoints"), endpoints("listen/endpoints")
        connect, listen = tuple(connect) or file_connect, tuple(listen) or file_listen
        if not connect and not listen:
            connect, listen = tuple(default_connect), tuple(default_listen)
        chosen = mode or (file_mode if file_mode in MODES else None) or ("client" if not listen else "router")
        return cls(mode=chosen, connect=connect, listen=listen, config_file=path)

    def security(self) -> BusSecurity | None:
        """What the role config secures (None without one)."""
        if self.config_file is None:
            return None
        return BusSecurity.of(_read_config_file(self.config_file))

    def listen_problem(self) -> str | None:
        """Why listening as configured would open the bus to other machines unguarded (None: it does not).

        Listening beyond loopback needs every such endpoint on TLS, with a certificate, client certificates
        required, a password dictionary and access rules (deny by default), from a role config file."""
        exposed = [e for e in self.listen if not is_loopback_endpoint(e)]
        if not exposed:
            return None
        security = self.security()
        plain = [e for e in exposed if e.partition("/")[0] not in TLS_PROTOCOLS]
        if security is not None and security.guards_listening and not plain:
            return None
        if plain:
            missing = f"{plain[0]} is not TLS"
        elif security is None:
            missing = "no --bus-config gives TLS, passwords and access rules"
        else:
            missing = f"{self.config_file} lacks " + ", ".join(
                what
                for what, present in (
                    ("a listen certificate", security.listen_certificate),
                    ("enable_mtls", security.client_certificates),
                    ("a password dictionary", security.password_dictionary),
                    ("access rules denying by default", security.access_control),
                )
                if not present
            )
        return (
            f"refusing to listen on {', '.join(exposed)} beyond this machine unauthenticated ({missing}): "
            f"make credentials with `studio bus credentials` and pass --bus-config <dir>/hub/bus.json5, "
            f"or accept the risk with {INSECURE_FLAG}"
        )

    @classmethod
    def hub(cls, listen: Iterable[str] = (DEFAULT_HUB_ENDPOINT,), connect: Iterable[str] = ()) -> BusConfig:
        """The UI host's configuration: a router (by default on loopback port 7447)."""
        return cls(mode="router", listen=tuple(listen), connect=tuple(connect))

    @classmethod
    def worker(
        cls, connect: Iterable[str] = (), listen: Iterable[str] = (), mode: Mode | None = None
    ) -> BusConfig:
        """A worker's configuration: a client of the hub unless it listens itself (then a peer)."""
        connect, listen = tuple(connect), tuple(listen)
        if not connect and not listen:
            connect = (DEFAULT_HUB_ENDPOINT,)
        if mode is None:
            mode = "peer" if listen else "client"
        return cls(mode=mode, connect=connect, listen=listen)

    @property
    def is_loopback_only(self) -> bool:
        return all(is_loopback_endpoint(e) for e in self.connect + self.listen)

    def zenoh_config(self) -> zenoh.Config:
        """The Zenoh configuration: the role config file's (if any) with this object's mode, endpoints, scouting
        and lease in place of the file's."""
        listen = list(self.listen)
        if self.mode == "peer" and not listen:
            listen = ["tcp/127.0.0.1:0"]  # Zenoh's own default would listen on every interface
        entries: dict[str, Any] = {
            "mode": self.mode,
            "connect": {
                "endpoints": list(self.connect),
                "timeout_ms": int(self.connect_timeout_s * 1000) if self.mode == "client" else -1,
                "exit_on_failure": self.mode == "client",
                "retry": {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2},
            },
            "listen": {"endpoints": listen},
            "scouting/multicast/enabled": bool(self.multicast_scouting),
            "transport/link/tx/lease": int(self.lease_ms),
            "transport/link/tx/keep_alive": 4,
        }
        if self.config_file is None:
            conf = zenoh.Config.from_json5("{}")
        else:
            conf = _read_config_file(self.config_file)
        for key, value in entries.items():
            conf.insert_json5(key, json.dumps(value))
        return conf

    def to_args(self) -> list[str]:
        """Command-line options that reproduce this configuration (for spawning a worker)."""
        args = ["--mode", self.mode]
        for e in self.connect:
            args += ["--connect", e]
        for e in self.listen:
            args += ["--listen", e]
        if self.multicast_scouting:
            args.append("--multicast-scouting")
        if self.config_file is not None:
            args += ["--bus-config", self.config_file]
        if self.insecure_listen:
            args.append(INSECURE_FLAG)
        return args


def add_bus_arguments(parser: argparse.ArgumentParser, role: Literal["worker", "hub"]) -> None:
    """``--connect`` / ``--listen`` / ``--mode`` / ``--multicast-scouting``, with the role's defaults."""
    default = (
        f"by default a client connecting to the hub at {DEFAULT_HUB_ENDPOINT}"
        if role == "worker"
        else f"by default a router listening on {DEFAULT_HUB_ENDPOINT} (this machine only)"
    )
    g = parser.add_argument_group("bus (Zenoh)", f"How this process joins the studio's bus: {default}.")
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tls/10.0.0.5:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on (repeatable); beyond loopback only tls/, with --bus-config, e.g. tls/0.0.0.0:7447",
    )
    mode_default = "client, or peer with --listen" if role == "worker" else "router"
    g.add_argument("--mode", choices=MODES, default=None, help=f"Zenoh mode (default: {mode_default})")
    g.add_argument(
        "--multicast-scouting", action="store_true", help="discover peers by UDP multicast (off by default)"
    )
    g.add_argument(
        "--bus-config",
        default=None,
        metavar="FILE",
        help="this role's Zenoh config from `studio bus credentials` (TLS, password, access rules; its "
        "endpoints unless --connect / --listen are given)",
    )
    g.add_argument(
        INSECURE_FLAG,
        dest="insecure_listen",
        action="store_true",
        help="listen beyond this machine WITHOUT encryption or authentication: anyone who reaches the port can "
        "submit jobs and read all traffic (refused otherwise)",
    )


def bus_config_from_args(args: argparse.Namespace, role: Literal["worker", "hub"]) -> BusConfig:
    """The configuration the bus options ask for; ValueError with one line if they make no sense."""
    if args.bus_config:
        cfg = BusConfig.from_file(
            args.bus_config,
            mode=args.mode,
            connect=args.connect,
            listen=args.listen,
            default_listen=(DEFAULT_HUB_ENDPOINT,) if role == "hub" else (),
            default_connect=(DEFAULT_HUB_ENDPOINT,) if role == "worker" else (),
        )
    elif role == "worker":
        cfg = BusConfig.worker(connect=args.connect, listen=args.listen, mode=args.mode)
    else:
        cfg = BusConfig(
            mode=args.mode or "router",
            connect=tuple(args.connect),
            listen=tuple(args.listen) or (DEFAULT_HUB_ENDPOINT,),
        )
    if args.multicast_scouting:
        cfg = replace(cfg, multicast_scouting=True)
    if args.insecure_listen:
        cfg = replace(cfg, insecure_listen=True)
    return cfg


def open_session(config: BusConfig) -> zenoh.Session:
    """Open a Zenoh session; raises :class:`BusError` with the endpoints in the message on failure, and with
    :meth:`BusConfig.listen_problem` for an unguarded listener beyond loopback (unless ``insecure_listen``)."""
    try:
        problem = config.listen_problem()
    except ValueError as e:
        raise BusError(str(e)) from None
    if problem is not None and not config.insecure_listen:
        raise BusError(problem)
    if problem is not None:
        log.warning(
            "INSECURE: listening on %s without encryption or authentication (%s): anyone who can reach it can "
            "submit jobs, drive teleop sessions and read all traffic",
            ", ".join(e for e in config.listen if not is_loopback_endpoint(e)),
            INSECURE_FLAG,
        )
    if not config.is_loopback_only:
        log.info("bus endpoints leave this machine: connect=%s listen=%s", config.connect, config.listen)
    try:
        conf = config.zenoh_config()
    except ValueError as e:
        raise BusError(str(e)) from None
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        where = ", ".join(config.connect + config.listen) or "(no endpoint)"
        hint = " — is the hub (`studio serve` / `studio hub`) running?" if config.mode == "client" else ""
        raise BusError(f"cannot open the bus as {config.mode} on {where}: {e}{hint}") from None


# ---------------------------------------------------------------------------------------------- helpers
class _RateLimitedLog:
    """Log at most one warning per key per interval (a flood of bad input must not flood the log)."""

    def __init__(self, interval_s: float = 2.0):
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(self, key: str, text: str, *args: Any) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -1e9) < self.interval_s:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                return
            self._last[key] = now
            suppressed = self._suppressed.pop(key, 0)
        more = f" ({suppressed} similar dropped)" if suppressed else ""
        log.warning(text + more, *args)


bad_input_log = _RateLimitedLog()

#: Largest request payload a queryable decodes unless it says otherwise (a forked recording can be megabytes).
MAX_REQUEST_BYTES = 64 << 20


def one_line(e: BaseException, *, with_type: bool = False, limit: int = 4000) -> str:
    """An exception as one line of text (its first line, shortened), for a log line or an error reply."""
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    if with_type or not first:
        first = f"{type(e).__name__}: {first}" if first else type(e).__name__
    return first[:limit]


M = TypeVar("M", bound=msg.Message)


def payload_bytes(zbytes: zenoh.ZBytes | None) -> bytes:
    return b"" if zbytes is None else zbytes.to_bytes()


@overload
def request(
    session: zenoh.Session,
    key: str,
    message: msg.Message,
    expect: type[M],
    *,
    timeout: float = 5.0,
    attachment: bytes | None = None,
) -> M: ...
@overload
def request(
    session: zenoh.Session,
    key: str,
    message: msg.Message,
    expect: tuple[type[msg.Message], ...],
    *,
    timeout: float = 5.0,
    attachment: bytes | None = None,
) -> msg.Message: ...
def request(
    session: zenoh.Session,
    key: str,
    message: msg.Message,
    expect: type[msg.Message] | tuple[type[msg.Message], ...],
    *,
    timeout: float = 5.0,
    attachment: bytes | None = None,
) -> msg.Message:
    """Send ``message`` as a query to ``key`` and return the first valid reply. ``attachment`` travels beside the
    message (a teleop session's owner token, see :mod:`studio.backend.sim_worker`).

    Raises :class:`RemoteError` if the answer is an ErrorReply, :class:`RequestTimeout` if the query timed out
    without a valid answer, and :class:`BusError` otherwise (nobody answered, or only with invalid replies).
    """
    problems: list[str] = []
    for reply in session.get(key, payload=msg.encode(message), timeout=timeout, attachment=attachment):
        if reply.ok is None:
            problems.append(payload_bytes(reply.err.payload).decode("utf-8", "replace"))
            continue
        try:
            answer = msg.decode(payload_bytes(reply.ok.payload))
        except msg.ProtocolError as e:
            problems.append(f"malformed reply: {e}")
            continue
        if isinstance(answer, msg.ErrorReply):
            raise RemoteError(answer.code, answer.message, key)
        if not isinstance(answer, expect):
            problems.append(f"unexpected reply {type(answer).__name__}")
            continue
        return answer
    detail = "; ".join(problems) if problems else "nobody answered"
    error = RequestTimeout if "Timeout" in problems else BusError
    raise error(f"{type(message).__name__} to {key} failed within {timeout:.1f} s: {detail}")


def request_all(
    session: zenoh.Session,
    selector: str,
    expect: type[M],
    message: msg.Message | None = None,
    *,
    timeout: float = 2.0,
) -> list[M]:
    """Every valid reply of type ``expect`` to a query on ``selector`` (malformed ones are logged).

    Replies are not consolidated: several replies on one key (a listing) all arrive.
    """
    out: list[M] = []
    kwargs: dict[str, Any] = {
        "timeout": timeout,
        "target": zenoh.QueryTarget.ALL,
        "consolidation": zenoh.ConsolidationMode.NONE,
    }
    if message is not None:
        kwargs["payload"] = msg.encode(message)
    for reply in session.get(selector, **kwargs):
        if reply.ok is None:
            continue
        try:
            out.append(msg.decode(payload_bytes(reply.ok.payload), expect))
        except msg.ProtocolError as e:
            bad_input_log.warning(f"reply:{selector}", "dropped a malformed reply to %s: %s", selector, e)
    return out


#: Returned by a queryable handler that keeps the query to answer it later (it must then call
#: :func:`reply` and ``query.drop()`` itself).
DEFERRED = object()

Reply = msg.Message | list[tuple[str, msg.Message]] | None


def reply(query: zenoh.Query, message: msg.Message, key: str | None = None) -> None:
    query.reply(key or str(query.key_expr), msg.encode(message))


def attachment_bytes(carrier: zenoh.Query | zenoh.Sample) -> bytes:
    """The attachment of a query or sample (empty without one)."""
    att = carrier.attachment
    return b"" if att is None else att.to_bytes()


@overload
def declare_queryable(
    session: zenoh.Session,
    key: str,
    handler: Callable[[M, zenoh.Query], Any],
    expect: type[M],
    *,
    max_bytes: int = ...,
) -> zenoh.Queryable: ...
@overload
def declare_queryable(
    session: zenoh.Session,
    key: str,
    handler: Callable[[msg.Message, zenoh.Query], Any],
    expect: tuple[type[msg.Message], ...],
    *,
    max_bytes: int = ...,
) -> zenoh.Queryable: ...
@overload
def declare_queryable(
    session: zenoh.Session,
    key: str,
    handler: Callable[[msg.Message | None, zenoh.Query], Any],
    expect: None = None,
    *,
    max_bytes: int = ...,
) -> zenoh.Queryable: ...
def declare_queryable(
    session: zenoh.Session,
    key: str,
    handler: Callable[[Any, zenoh.Query], Any],
    expect: type[msg.Message] | tuple[type[msg.Message], ...] | None = None,
    *,
    max_bytes: int = MAX_REQUEST_BYTES,
) -> zenoh.Queryable:
    """A queryable whose handler receives the decoded request (None without payload).

    With ``expect`` the request is always decoded (and checked to be one of those types), so the handler
    never receives None. The handler returns a message (the reply), a list of (key, message) replies,
    None (no reply) or :data:`DEFERRED`. Malformed requests, and requests larger than ``max_bytes``, get
    ``ErrorReply("bad_request")`` and one rate-limited warning line; a handler that raises ``ValueError`` gets
    ``ErrorReply("bad_request")`` with its message, any other exception ``ErrorReply("internal")``, each logged
    as one rate-limited line (the traceback at DEBUG) — the process keeps serving.
    """

    def on_query(query: zenoh.Query) -> None:
        deferred = False
        try:
            data = payload_bytes(query.payload)
            if len(data) > max_bytes:
                bad_input_log.warning(
                    f"query:{key}",
                    "rejected a request of %d bytes on %s (at most %d)",
                    len(data),
                    key,
                    max_bytes,
                )
                reply(
                    query,
                    msg.ErrorReply(code="bad_request", message=f"request larger than {max_bytes} bytes"),
                )
                return
            request_msg = None
            if data or expect is not None:
                try:
                    request_msg = msg.decode(data, expect) if expect is not None else msg.decode(data)
                except msg.ProtocolError as e:
                    bad_input_log.warning(
                        f"query:{key}", "rejected a malformed request on %s: %s", query.key_expr, e
                    )
                    reply(query, msg.ErrorReply(code="bad_request", message=str(e)[:4000]))
                    return
            try:
                answer = handler(request_msg, query)
            except ValueError as e:
                text = one_line(e)
                bad_input_log.warning(f"refused:{key}", "refused a request on %s: %s", query.key_expr, text)
                reply(query, msg.ErrorReply(code="bad_request", message=text))
                return
            except Exception as e:
                text = one_line(e, with_type=True)
                bad_input_log.warning(f"failed:{key}", "a request on %s failed: %s", query.key_expr, text)
                log.debug("a request on %s failed", query.key_expr, exc_info=True)
                reply(query, msg.ErrorReply(code="internal", message=text))
                return
            if answer is DEFERRED:
                deferred = True
            elif isinstance(answer, list):
                for k, m in answer:
                    reply(query, m, k)
            elif answer is not None:
                reply(query, answer)
        except Exception:
            log.exception("could not answer a query on %s", key)
        finally:
            if not deferred:
                query.drop()

    return session.declare_queryable(key, on_query)


@overload
def declare_subscriber(
    session: zenoh.Session,
    key: str,
    callback: Callable[[M, zenoh.Sample], None],
    expect: type[M],
    **kwargs: Any,
) -> zenoh.Subscriber: ...
@overload
def declare_subscriber(
    session: zenoh.Session,
    key: str,
    callback: Callable[[msg.Message, zenoh.Sample], None],
    expect: tuple[type[msg.Message], ...] | None = None,
    **kwargs: Any,
) -> zenoh.Subscriber: ...
def declare_subscriber(
    session: zenoh.Session,
    key: str,
    callback: Callable[[Any, zenoh.Sample], None],
    expect: type[msg.Message] | tuple[type[msg.Message], ...] | None = None,
    **kwargs: Any,
) -> zenoh.Subscriber:
    """A subscriber that hands decoded, validated messages to ``callback``; bad samples are logged and
    dropped, and an exception in ``callback`` is logged (the subscription stays alive)."""

    def on_sample(sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            message = (
                msg.decode(payload_bytes(sample.payload), expect)
                if expect
                else msg.decode(payload_bytes(sample.payload))
            )
        except msg.ProtocolError as e:
            bad_input_log.warning(f"sub:{key}", "dropped a malformed message on %s: %s", sample.key_expr, e)
            return
        try:
            callback(message, sample)
        except Exception as e:
            text = one_line(e, with_type=True)
            bad_input_log.warning(
                f"callback:{key}", "a message on %s could not be handled: %s", sample.key_expr, text
            )
            log.debug("a message on %s could not be handled", sample.key_expr, exc_info=True)

    return session.declare_subscriber(key, on_sample, **kwargs)


@dataclass
class Latest:
    """A one-slot mailbox: writers replace the value, readers wait for a newer one (latest wins)."""

    value: Any = None
    version: int = 0
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def put(self, value: Any) -> None:
        with self._cond:
            self.value = value
            self.version += 1
            self._cond.notify_all()

    def get(self) -> tuple[Any, int]:
        with self._cond:
            return self.value, self.version

    def wait_until(self, predicate: Callable[[Any], bool], timeout: float) -> Any:
        """Wait until ``predicate(value)`` holds; returns the value, or None after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.value is None or not predicate(self.value):
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self.value

    def wait_newer(self, version: int, timeout: float) -> tuple[Any, int]:
        """Wait until the version exceeds ``version`` (or the timeout passes); return (value, version)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.version <= version:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            return self.value, self.version
