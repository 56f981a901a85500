"""The line the panels show about a demonstration's score: how far it is from what the policy learnt from.

The score and its calibrated threshold come from the plan or rollout job (:mod:`studio.eval.demo_score`); this
module only words them: a quiet line when the demonstration is like the policy's held-out ones, a warning when it
is far from them, and the reason when there is no score.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

WARNING = "⚠ **This demonstration is far from what the policy learnt from**"


def demo_score_note(score: Mapping[str, Any] | None) -> str:
    """One line for a job's ``demo_score`` (``{"score", "threshold", "familiar", "calibration"}`` or
    ``{"unavailable": reason}``); "" for None (a job from before scores were kept)."""
    if not score:
        return ""
    if "unavailable" in score:
        return f"Demonstration score: none ({score['unavailable']})."
    value, threshold = float(score["score"]), float(score["threshold"])
    calibrated = (
        f"threshold {threshold:.2f}, calibrated on {score.get('calibration') or 'held-out demonstrations'}"
    )
    if score.get("familiar", value <= threshold):
        return (
            f"Demonstration score {value:.2f} ({calibrated}): like the demonstrations the policy learnt from."
        )
    return (
        f"{WARNING} (score {value:.2f} > {calibrated}): its plan may mean nothing — check that the video shows "
        "the task."
    )
