"""The sentence the panels put under a plan some of whose waypoints the model put outside the workspace.

The scene draws a plan's waypoints at the targets the controller commands
(:func:`studio.sim.waypoints.commanded_waypoints`: clipped to the workspace and the scene's own bounds), which is
where the arm goes; a guided plan may extrapolate far outside (below the table, past its far edge), and this says
which waypoints and how far.
"""

from __future__ import annotations

import numpy as np


def workspace_note(predicted: np.ndarray, commanded: np.ndarray, tolerance: float = 0.01) -> str:
    """A sentence naming the waypoints the model put outside the workspace (more than ``tolerance`` metres from the
    target the controller commands, :func:`studio.sim.waypoints.commanded_waypoints`), which the scene draws where
    the arm is sent; '' when every waypoint is inside."""
    off = np.linalg.norm(np.asarray(predicted)[:, :3] - np.asarray(commanded)[:, :3], axis=1)
    far = [str(i + 1) for i in np.flatnonzero(off > tolerance)]
    if not far:
        return ""
    names = far[0] if len(far) == 1 else ", ".join(far[:-1]) + " and " + far[-1]
    return (
        f" The model put waypoint{'s' if len(far) > 1 else ''} {names} outside the workspace (up to "
        f"{off.max() * 100:.0f} cm out): drawn where the arm is sent."
    )
