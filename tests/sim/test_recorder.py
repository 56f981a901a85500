"""The span of a person's recording that holds the demonstration: idle ticks at either end are left out."""

import numpy as np

from studio.sim.recorder import LEAD_IN_S, LEAD_OUT_S, active_span

DT = 0.01


def rows(ee: np.ndarray, grip: np.ndarray) -> list[dict]:
    return [{"ee_pos_world": e, "gripper_cmd": g} for e, g in zip(ee, grip, strict=True)]


def test_idle_ticks_before_the_first_motion_and_after_the_last_are_left_out():
    idle, move, rest = 300, 100, 200
    x = np.concatenate([np.zeros(idle), np.linspace(0, 0.2, move), np.full(rest, 0.2)])
    ee = np.stack([x, np.zeros_like(x), np.full_like(x, 0.25)], axis=1)
    start, end = active_span(rows(ee, np.zeros(len(x))), DT)
    first_moved = idle + int(np.argmax(np.linspace(0, 0.2, move) > 0.01))
    last_moved = idle + int(np.nonzero(np.abs(np.linspace(0, 0.2, move) - 0.2) > 0.01)[0][-1])
    assert start == first_moved - round(LEAD_IN_S / DT)
    assert end == last_moved + 1 + round(LEAD_OUT_S / DT)


def test_a_gripper_command_counts_as_motion_and_a_still_recording_is_kept_whole():
    ee = np.zeros((500, 3))
    grip = np.zeros(500)
    grip[250:] = 1.0  # closed in place: the fingers move though the grasp point does not
    start, end = active_span(rows(ee, grip), DT)
    assert start == 250 - round(LEAD_IN_S / DT) and end == 250 + round(LEAD_OUT_S / DT)
    assert active_span(rows(ee, np.zeros(500)), DT) == (0, 500)
    assert active_span([], DT) == (0, 0)
