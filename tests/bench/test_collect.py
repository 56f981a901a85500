"""`studio bench collect` on a tiny configuration: real collection and a real data loader, keys and units."""

from __future__ import annotations

import argparse

from studio.bench import collect as bench


def test_collect_bench_tiny():
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(
        [
            "--scene",
            "push",
            "--workers",
            "1",
            "--image-size",
            "48",
            "64",
            "--train-size",
            "24",
            "32",
            "--loader-workers",
            "0",
            "--loader-batches",
            "2",
            "--batch-size",
            "4",
        ]
    )
    out = bench.measure(args)
    assert out["tasks"] == 3
    assert out["workers_1"]["episodes"] == 6  # one per training task and robot
    assert out["episodes_per_min"]["1"] > 0
    assert out["projected_full_set_min"] == round(bench.FULL_SET_EPISODES / out["episodes_per_min"]["1"], 1)
    assert out["train_samples_per_s"] > 0 and out["pairs"] == 3
