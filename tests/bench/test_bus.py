"""`studio bench bus --phases jobs`: job submission timed at several queue lengths, and the idle queue's cost."""

from __future__ import annotations

import argparse

import pytest

from studio.bench import bus as bus_bench

pytestmark = pytest.mark.timeout(120)


def test_job_phase_reports_submission_rates_per_queue_length_and_idle_cpu():
    parser = argparse.ArgumentParser()
    bus_bench.add_arguments(parser)
    args = parser.parse_args(["--phases", "jobs", "--queued", "10,600", "--submits", "50"])
    out = bus_bench.measure(args)
    assert set(out) == {
        "job_submit_per_s_at_10_queued",
        "job_submit_per_s_at_600_queued",
        "job_queue_idle_cpu",
        "job_queue_jobs",
        "job_journal_bytes",
    }
    assert out["job_queue_jobs"] == 650 and out["job_journal_bytes"] > 0
    assert out["job_submit_per_s_at_600_queued"] > out["job_submit_per_s_at_10_queued"] / 3
    assert out["job_queue_idle_cpu"] < 0.05
    with pytest.raises(SystemExit, match="unknown phases"):
        bus_bench.measure(parser.parse_args(["--phases", "teleop,nope"]))
