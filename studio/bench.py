"""`studio bench TARGET`: dispatches to the benchmark that lives with the code it measures."""

from __future__ import annotations

import argparse
import importlib
import json
import sys

# target -> module exposing add_arguments(parser) and measure(args) -> dict
TARGETS: dict[str, str] = {
    "sim": "studio.sim.bench",
    "model": "studio.model.bench",
    "follow": "studio.model.follow_bench",
    "plan": "studio.model.plan_bench",
    "collect": "studio.data.bench",
    "bus": "studio.backend.bench",
    "metaworld": "studio.sim.metaworld_bench",
    "ui": "studio.ui.bench",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("target", choices=sorted(TARGETS), help="what to measure")
    parser.add_argument("--json", action="store_true", help="print only the JSON object")
    parser.add_argument("rest", nargs=argparse.REMAINDER, help="options of the chosen benchmark")


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(TARGETS[args.target])
    sub = argparse.ArgumentParser(prog=f"studio bench {args.target}")
    module.add_arguments(sub)
    sub_args = sub.parse_args([a for a in args.rest if a != "--json"])
    result = module.measure(sub_args)
    compact = args.json or "--json" in args.rest
    text = json.dumps(result, indent=None if compact else 2, sort_keys=True)
    sys.stdout.write(text + "\n")
    return 0
