"""`studio serve`: the studio in the browser — hub, embedded workers and the viser app — and print its URL.

    studio serve [--host 127.0.0.1] [--port 8080] [--data-dir DIR] [--workers embedded|none] [--listen ENDPOINT]

Everything stays on this machine by default: the web server binds to 127.0.0.1 and the bus router listens
on ``tcp/127.0.0.1:7447``. Serving other machines is an explicit choice (``--host 0.0.0.0``; workers on
other machines need the bus credentials of ``studio bus credentials``: ``--bus-config hub/bus.json5``, see
docs/deployment.md). ``--workers none`` starts no
worker, so that external ones (``studio worker sim|train``) do the work.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import replace

from studio.backend import bus
from studio.backend.stopping import StopSignals
from studio.data.paths import add_data_dir_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="interface to bind; 127.0.0.1 (default) keeps the studio on this machine",
    )
    parser.add_argument(
        "--port", type=int, default=8080, help="web port (the next free one is used if taken)"
    )
    add_data_dir_argument(parser)
    parser.add_argument(
        "--workers",
        choices=("embedded", "default", "none"),
        default="embedded",
        help="embedded (default, alias: default): start one sim worker and one trainer here; none: wait for "
        "external workers",
    )
    parser.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    bus.add_bus_arguments(parser, "hub")


def run(args: argparse.Namespace) -> int:
    from studio.ui.app import StudioApp

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = bus.bus_config_from_args(args, "hub")
    except ValueError as e:
        print(f"studio serve: {e}", file=sys.stderr)
        return 2
    bus_note = ""
    busy = [e for e in config.listen if bus.endpoint_in_use(e)]
    if busy and not args.listen:
        # Another studio (or hub) on this machine has the default bus port: listen on a free one, as the web
        # port does, and say so (workers started by hand must connect there).
        endpoint = bus.loopback_endpoint(bus.free_loopback_port())
        config = replace(config, listen=(endpoint,))
        bus_note = f" — port {bus.DEFAULT_PORT} was taken; start other workers with --connect {endpoint}"
    elif busy:
        print(
            f"studio serve: the bus endpoint {busy[0]} is already in use (another studio or hub on this machine?); "
            f"pass a free one, e.g. --listen {bus.loopback_endpoint(bus.free_loopback_port())}",
            file=sys.stderr,
        )
        return 1
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"studio serve: serving on {args.host} — other machines can reach this studio", file=sys.stderr)
    try:
        app = StudioApp(
            host=args.host,
            port=args.port,
            data_dir=args.data_dir,
            bus_config=config,
            workers="none" if args.workers == "none" else "embedded",
        )
    except bus.BusError as e:
        print(f"studio serve: {e}", file=sys.stderr)
        return 1
    signals = StopSignals("studio serve")
    workers = (
        "one sim worker and one trainer"
        if args.workers != "none"
        else "no workers (waiting for external ones)"
    )
    print(
        f"OSVI Studio running at {app.url}  (data: {app.data_dir}; bus: {', '.join(config.listen)}{bus_note}; "
        f"{workers}; "
        "Ctrl+C to stop)",
        flush=True,
    )
    try:
        signals.wait_for_stop()
    finally:
        with signals.stopping():
            app.stop()
    return 0
