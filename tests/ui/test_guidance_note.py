"""The sentence under a guided policy's plan: nothing without guidance; guided with the gain against the gate and
how far the plan moved; not guided below the gate."""

from __future__ import annotations

from studio.ui.guidance_note import guidance_note


def test_no_guidance_says_nothing():
    assert guidance_note(None) == "" and guidance_note({}) == ""


def test_a_guided_plan_names_the_scale_the_gain_against_the_gate_and_how_far_it_moved():
    text = guidance_note({"scale": 5.0, "gate": 1.04, "gain": 1.2431, "guided": True}, 0.314)
    assert "Grey: the plan from the scene alone" in text
    assert "guidance 5 moved the plan up to 0.31 m from it (demonstration gain 1.243 ≥ gate 1.04)." in text
    # ungated (no gate), and a stored rollout that keeps neither scale nor gate
    assert guidance_note({"scale": 3.0, "gate": 0.0, "gain": 0.9, "guided": True}).endswith(
        "guidance 3 moved the plan (demonstration gain 0.900)."
    )
    assert guidance_note({"gain": 1.6, "guided": True}, 0.12).endswith(
        "guidance moved the plan up to 0.12 m from it (demonstration gain 1.600)."
    )


def test_a_plan_below_the_gate_says_it_is_the_demonstrations_alone():
    text = guidance_note({"scale": 5.0, "gate": 1.04, "gain": 0.985, "guided": False}, 0.5)
    assert "not guided: demonstration gain 0.985 is below the policy's gate 1.04" in text
    assert "moved" not in text and text.endswith("the plan is the demonstration's alone.")
    assert "below the policy's gate," in guidance_note({"gain": 0.9, "guided": False})


def test_a_plan_guided_by_the_surprise_gate_says_so_and_one_below_both_gates_names_both():
    guided = guidance_note(
        {"scale": 5.0, "gate": 1.2, "gain": 1.037, "guided": True, "surprise": 8.731, "surprise_gate": 7.55},
        0.41,
    )
    assert guided.endswith(
        "guidance 5 moved the plan up to 0.41 m from it (demonstration gain 1.037 is below the gate, but the world "
        "model's surprise at it is 8.73 ≥ 7.55)."
    )
    calm = guidance_note(
        {"scale": 5.0, "gate": 1.2, "gain": 1.037, "guided": False, "surprise": 6.2, "surprise_gate": 7.55}
    )
    assert "below the policy's gate 1.2, and its surprise 6.20 below the surprise gate 7.55" in calm
    # a stored rollout keeps the gain and the surprise, not the gates
    assert guidance_note({"gain": 1.037, "guided": True, "surprise": 8.731}).endswith(
        "(demonstration gain 1.037; surprise 8.73)."
    )
