"""`studio bench follow` trains each layout variant on the synthetic task and reports validation points."""

from __future__ import annotations

import argparse

import pytest

from studio.model import follow_bench


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    follow_bench.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_reports_errors_and_demonstration_effect_per_variant():
    result = follow_bench.measure(_args("--steps", "4", "--val-points", "2", "--variants", "paper,divided+cells (cpu)"))
    assert set(result["variants"]) == {"paper", "divided+cells (cpu)"}
    for v in result["variants"].values():
        assert [p["step"] for p in v["val"]] == [2, 4]
        assert all(p["final_err_m"] > 0 and p["demo_effect_m"] >= 0 for p in v["val"])
    assert 0.15 < result["mean_target_final_err_m"] < 0.2


def test_unknown_variant_is_a_clear_error():
    with pytest.raises(SystemExit, match="unknown variant"):
        follow_bench.measure(_args("--variants", "paper,transformer-xl"))
