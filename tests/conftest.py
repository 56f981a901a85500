"""Suite-wide pytest hooks, and the fixtures several test directories share.

The ``slow`` marker (pyproject.toml: "takes more than ~20 s") lets ``./run test -m "not slow"`` be a quick
run. So that the marker keeps up with the tests, the terminal summary lists tests that took longer than that
(setup and teardown included) without it. It is a hint only: no test ever fails because of its duration.

A test that hangs where pytest-timeout's signal cannot reach it (a native call that holds the interpreter
lock never lets the Python handler run) would stall the whole run silently: pyproject.toml arms pytest's
faulthandler watchdog (in C) past the longest per-test timeout, which prints every thread's stack and ends
the run, so the log says where it stuck.

``./run test`` runs the suite in two runs, one after the other, each spreading its test files over two worker
processes: everything but the browser tests, then the browser tests (``STUDIO_TEST_PART=rest|browser`` selects
the part here). A full run leaves, after 800 tests,
a process whose state the browser tests should not inherit: they start their app, workers and Chromium in a
process of their own, as a person's studio would.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

SLOW_S = 20.0

_seconds: dict[str, float] = {}
_unmarked: set[str] = set()


PART_VARIABLE = "STUDIO_TEST_PART"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    part = os.environ.get(PART_VARIABLE, "")
    if part not in ("", "rest", "browser"):
        raise pytest.UsageError(f"{PART_VARIABLE} must be 'rest' or 'browser', not {part!r}")
    if not part:
        return
    keep = [item for item in items if (item.get_closest_marker("browser") is not None) == (part == "browser")]
    dropped = [item for item in items if item not in keep]
    if dropped:
        config.hook.pytest_deselected(items=dropped)
        items[:] = keep


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _seconds[report.nodeid] = _seconds.get(report.nodeid, 0.0) + report.duration
    if "slow" not in report.keywords:
        _unmarked.add(report.nodeid)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    late = sorted(((s, n) for n, s in _seconds.items() if s > SLOW_S and n in _unmarked), reverse=True)
    if not late:
        return
    terminalreporter.write_sep("-", f"over {SLOW_S:.0f} s without @pytest.mark.slow (consider marking them)")
    for seconds, nodeid in late:
        terminalreporter.write_line(f"{seconds:7.1f} s  {nodeid}")


class _MissPlanner:
    """Plans empty air beside the pick-and-place objects: a rollout that fails at the reach stage."""

    def plan(self, expert_frames, agent_frame, K, T_world_cam):
        wps = np.array(
            [
                [0.3, 0.8, 0.1, 1],
                [0.3, 0.8, 0.15, 1],
                [0.3, 0.8, 0.15, 0],
                [0.3, 0.8, 0.15, 0],
                [0.3, 0.8, 0.2, 0],
            ],
            dtype=float,
        )
        return type("Plan", (), {"waypoints_world": wps})()


@pytest.fixture(scope="session")
def miss_planner() -> _MissPlanner:
    """A planner whose rollouts fail at the reach stage (for tests that need a failed rollout to inspect)."""
    return _MissPlanner()
