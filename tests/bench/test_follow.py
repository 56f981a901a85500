"""`studio bench follow` trains each layout variant on the synthetic task and reports validation points."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from studio.bench import follow as follow_bench


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    follow_bench.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_reports_errors_and_demonstration_effect_per_variant():
    result = follow_bench.measure(
        _args("--steps", "4", "--val-points", "2", "--variants", "paper,divided+cells (cpu)")
    )
    assert set(result["variants"]) == {"paper", "divided+cells (cpu)"}
    for v in result["variants"].values():
        assert [p["step"] for p in v["val"]] == [2, 4]
        assert all(p["final_err_m"] > 0 and p["demo_effect_m"] >= 0 for p in v["val"])
    assert 0.15 < result["mean_target_final_err_m"] < 0.2


def test_unknown_variant_is_a_clear_error():
    with pytest.raises(SystemExit, match="unknown variant"):
        follow_bench.measure(_args("--variants", "paper,transformer-xl"))


def test_match_task_shuffles_markers_and_the_path_ends_at_the_demonstrated_colour():
    from studio.bench.synthetic_task import TARGETS_CAM, SyntheticPairs

    data = SyntheticPairs(n_tasks=4, episodes_per_task=6, shuffle_targets=True)
    assert data.fingerprint() != SyntheticPairs(n_tasks=4, episodes_per_task=6).fingerprint()
    moved = 0
    for i in range(0, len(data), 7):
        task, e, a = data.pairs[i]
        ex_layout, ag_layout = data._layout(task, e, 0), data._layout(task, a, 1)
        assert sorted(ag_layout) == [0, 1, 2, 3]
        end = data[i]["path"][-1, :3]
        assert np.allclose(
            end, TARGETS_CAM[ag_layout[task]], atol=1e-6
        )  # the agent's marker of the task's colour
        moved += int(ex_layout[task] != ag_layout[task])
    assert moved > 0  # copying the demonstration's end point is not the answer


def test_match_variant_runs_with_and_without_the_demonstration_task_loss():
    result = follow_bench.measure(
        _args(
            "--task",
            "match",
            "--episodes",
            "2",
            "--steps",
            "2",
            "--val-points",
            "1",
            "--variants",
            "cross+cells 2 blocks",
        )
    )
    assert result["task"] == "match" and result["episodes_per_task"] == 2 and result["demo_task_weight"] == 0
    point = result["variants"]["cross+cells 2 blocks"]["val"][0]
    assert point["step"] == 2 and "task_acc" not in point
    result = follow_bench.measure(
        _args(
            "--task",
            "match",
            "--episodes",
            "2",
            "--steps",
            "2",
            "--val-points",
            "1",
            "--variants",
            "divided+cells 2 blocks",
            "--demo-task-weight",
            "1",
        )
    )
    assert result["demo_task_weight"] == 1.0
    assert 0 <= result["variants"]["divided+cells 2 blocks"]["val"][0]["task_acc"] <= 1
