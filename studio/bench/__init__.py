"""`studio bench TARGET`: the benchmarks, one module per target, and the command that dispatches to them.

Benchmarks measure the product (simulation and rendering rates, model throughput, collection speed, bus latency,
what a plan depends on) and print one JSON object. They sit above every other package: a benchmark may drive the
simulator, the model, the store, the bus or the browser UI, and nothing in the product imports a benchmark.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

# target -> module exposing add_arguments(parser) and measure(args) -> dict
TARGETS: dict[str, str] = {
    "sim": "studio.bench.sim",
    "model": "studio.bench.model",
    "follow": "studio.bench.follow",
    "plan": "studio.bench.plan",
    "collect": "studio.bench.collect",
    "bus": "studio.bench.bus",
    "metaworld": "studio.bench.metaworld",
    "ui": "studio.bench.ui",
    "click-demo": "studio.bench.click_demo",
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
