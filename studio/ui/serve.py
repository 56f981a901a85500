"""`studio serve`: start the browser studio and print its URL (loopback unless told otherwise)."""

from __future__ import annotations

import argparse
import time

from studio.data.paths import add_data_dir_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="interface to bind; 127.0.0.1 (default) keeps the studio on this machine")
    parser.add_argument("--port", type=int, default=8080, help="port (the next free one is used if taken)")
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    from studio.ui.app import StudioApp

    app = StudioApp(host=args.host, port=args.port, data_dir=args.data_dir)
    print(f"OSVI Studio running at {app.url}  (data: {app.store.root}; Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
    return 0
