"""The sentence the panels put under a guided policy's plan: guided or not, the demonstration's gain, the gate.

A policy planned with demonstration guidance (``studio.model.guidance``) also plans from the scene alone; the
panels draw that plan in grey and say here whether the shown plan was guided and why (the demonstration's gain
against the policy's gate, when it has one).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def guidance_note(guidance: Mapping[str, Any] | None, moved_m: float | None = None) -> str:
    """A leading-space sentence for ``guidance`` = {"guided", "gain", and optionally "scale", "gate"} (None: "").

    ``moved_m``: how far guidance moved the plan from the null plan (largest waypoint distance), if known.
    """
    if not guidance:
        return ""
    gain, gate, scale = guidance.get("gain"), guidance.get("gate"), guidance.get("scale")
    gain_text = f"demonstration gain {float(gain):.3f}" if gain is not None else ""
    text = " Grey: the plan from the scene alone (the null demonstration);"
    if guidance.get("guided", True):
        reason = f"{gain_text} ≥ gate {float(gate):g}" if gain_text and gate else gain_text
        moved = f" up to {moved_m:.2f} m from it" if moved_m is not None else ""
        scaled = f" {float(scale):g}" if scale else ""
        return text + f" guidance{scaled} moved the plan{moved}" + (f" ({reason})." if reason else ".")
    below = f"below the policy's gate {float(gate):g}" if gate else "below the policy's gate"
    return (
        text
        + f" not guided: {gain_text or 'the demonstration gain'} is {below}, so the plan is the demonstration's alone."
    )
