"""The sentence the panels put under a guided policy's plan: guided or not, the demonstration's gain, the gate.

A policy planned with demonstration guidance (``studio.model.guidance``) also plans from the scene alone; the
panels draw that plan in grey and say here whether the shown plan was guided and why (the demonstration's gain
against the policy's gate, when it has one, or the demonstration's surprise against the policy's surprise gate).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def guidance_note(guidance: Mapping[str, Any] | None, moved_m: float | None = None) -> str:
    """A leading-space sentence for ``guidance`` = {"guided", "gain", and optionally "scale", "gate", "surprise",
    "surprise_gate"} (None: "").

    ``moved_m``: how far guidance moved the plan from the null plan (largest waypoint distance), if known.
    """
    if not guidance:
        return ""
    gain, gate, scale = guidance.get("gain"), guidance.get("gate"), guidance.get("scale")
    gain_text = f"demonstration gain {float(gain):.3f}" if gain is not None else ""
    surprise, surprise_gate = guidance.get("surprise"), guidance.get("surprise_gate")
    text = " Grey: the plan from the scene alone (the null demonstration);"
    if guidance.get("guided", True):
        reason = f"{gain_text} ≥ gate {float(gate):g}" if gain_text and gate else gain_text
        if surprise is not None and gain is not None and gate and float(gain) < float(gate):
            # guided by the surprise gate: the gain alone would have left it
            reason = f"{gain_text} is below the gate, but the world model's surprise at it is {float(surprise):.2f}"
            reason += f" ≥ {float(surprise_gate):g}" if surprise_gate else ""
        elif surprise is not None:
            reason += ("; " if reason else "") + f"surprise {float(surprise):.2f}"
        moved = f" up to {moved_m:.2f} m from it" if moved_m is not None else ""
        scaled = f" {float(scale):g}" if scale else ""
        return text + f" guidance{scaled} moved the plan{moved}" + (f" ({reason})." if reason else ".")
    below = f"below the policy's gate {float(gate):g}" if gate else "below the policy's gate"
    if surprise is not None:
        below += f", and its surprise {float(surprise):.2f} below " + (
            f"the surprise gate {float(surprise_gate):g}" if surprise_gate else "the surprise gate"
        )
    return (
        text
        + f" not guided: {gain_text or 'the demonstration gain'} is {below}, so the plan is the demonstration's alone."
    )
