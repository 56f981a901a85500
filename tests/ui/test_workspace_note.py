"""The sentence under a plan whose waypoints the model put outside the workspace."""

import numpy as np

from studio.ui.workspace_note import workspace_note


def test_the_status_names_waypoints_the_model_put_outside_the_workspace():
    predicted = np.array([[0.0, 0.5, 0.2, 0], [0.0, 0.5, -0.2, 1], [0.6, 0.5, 0.2, 1], [0.0, 0.5, 0.205, 0]])
    commanded = predicted.copy()
    commanded[1, 2], commanded[2, 0], commanded[3, 2] = 0.012, 0.45, 0.2  # the last 5 mm off: inside
    assert workspace_note(predicted, commanded) == (
        " The model put waypoints 2 and 3 outside the workspace (up to 21 cm out): drawn where the arm is sent."
    )
    assert workspace_note(predicted[2:], commanded[2:]).startswith(
        " The model put waypoint 1 outside the workspace (up to 15 cm out)"
    )
    assert workspace_note(predicted, predicted) == ""
