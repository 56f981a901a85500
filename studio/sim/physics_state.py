"""The physics state an episode keeps per control tick, and the check that a stored one fits a model.

A recording keeps MuJoCo's *integration* state (time, positions, velocities, actuator and control values,
warm-start accelerations, applied forces, mocap poses) at every tick: everything the next step depends
on, so setting it and stepping on with the same commands continues the episode bit for bit.
"""

from __future__ import annotations

import mujoco
import numpy as np

#: The MuJoCo state a recording keeps per tick and a restore sets.
STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION


def state_size(model: mujoco.MjModel) -> int:
    """Numbers per tick of :data:`STATE_SPEC` for ``model``."""
    return int(mujoco.mj_stateSize(model, STATE_SPEC))


def check_states(model: mujoco.MjModel, states: np.ndarray) -> None:
    """Raise ValueError unless ``states`` is a non-empty, finite (T, S) array of ``model``'s states."""
    states = np.asarray(states)
    size = state_size(model)
    if states.ndim != 2 or len(states) == 0:
        raise ValueError(f"expected a (ticks, {size}) array of physics states, got shape {states.shape}")
    if states.shape[1] != size:
        raise ValueError(
            f"the recorded physics states have {states.shape[1]} numbers per tick, this scene's model has "
            f"{size}: the scene changed since the episode was recorded, so it cannot be restored exactly"
        )
    if not np.all(np.isfinite(states)):
        raise ValueError("the recorded physics states contain non-finite numbers")
