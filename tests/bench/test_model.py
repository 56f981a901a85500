"""`studio bench model` returns the documented keys (timings are not asserted: they belong to benchmarks)."""

from __future__ import annotations

import argparse

import torch

from studio.bench import model as bench

torch.set_num_threads(1)


def test_measure_reports_throughput_latency_and_size():
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(
        ["--config", "cpu", "--image-size", "96x128", "--reps", "1", "--warmup", "0", "--threads", "1"]
    )
    result = bench.measure(args)
    for key in ("train_samples_per_s", "train_samples_per_s_shared_expert", "plan_latency_ms", "replan_ms"):
        assert result[key] > 0
    assert result["image_size"] == [96, 128] and result["state_shape"] == [
        64,
        12,
        16,
    ]  # cpu: trunk to layer2, stride 8
    assert result["params"] > 1_000_000 and result["batch"] == 2 and result["n_expert"] == 10
    assert result["reference"]["train_samples_per_s"] == 2.5 and "fwd_bwd_speedup_vs_reference_min" in result
    profile = result["step_profile_ms"]
    assert set(profile) == {
        "augment",
        "encoder_fwd_bwd",
        "targets_fwd",
        "step_fwd_bwd",
        "rest_fwd_bwd",
        "optimizer",
    }
    assert profile["step_fwd_bwd"] >= profile["encoder_fwd_bwd"] > 0 and profile["targets_fwd"] > 0
