"""The Imitate panel's refresh: what it says when a scripted demonstration it made arrives."""

from types import SimpleNamespace

import numpy as np

from studio.ui.panels.imitate import ImitatePanel


def _element(**attrs) -> SimpleNamespace:
    return SimpleNamespace(visible=False, content="", image=None, label="", **attrs)


def _panel_showing_a_plan_of(demo: str, made: str) -> ImitatePanel:
    """An Imitate panel (no viser) whose plan of ``demo`` is shown while the scripted demonstration ``made``,
    which it asked for, has just been stored."""
    panel = ImitatePanel.__new__(ImitatePanel)
    frames = np.zeros((12, 8, 8, 3), np.uint8)
    panel.app = SimpleNamespace(
        dataset_version=1,
        dataset_changed=lambda: None,
        store=SimpleNamespace(load_frames=lambda eid: frames),
        hub=SimpleNamespace(jobs=SimpleNamespace(jobs=lambda: [])),
    )
    panel.tab = SimpleNamespace(mode="imitate", token=3, view=SimpleNamespace(clear_overlay=lambda *a: None))
    panel._rollout_token = None
    panel.tab.view.show_null_plan = lambda *a: None
    panel.labels = {"pick_place/bar->blue": "pick_place/bar->blue"}
    panel.task = SimpleNamespace(value="pick_place/bar->blue")
    options = (f"{demo} · scripted · sawyer", f"{made} · scripted · sawyer")
    panel.demo = SimpleNamespace(value=options[0], options=options)
    panel._demo_version = 1
    panel._shown = {}
    panel.rollout = None
    panel.expert_job = SimpleNamespace(terminal=True, state="succeeded", result={"episode_id": made})
    panel.plan_job = SimpleNamespace(spec={"expert_episode_id": demo})
    panel.plan_wps = np.zeros((5, 4))
    panel._agent_frame, panel._latents, panel._expert_frames = np.zeros((8, 8, 3)), np.zeros(1), frames
    panel._frames_of = demo
    for name in ("status", "score_note", "outcome", "latent_note", "watch"):
        setattr(panel, name, _element())
    for name in ("expert_strip", "agent_image", "latent_strip", "enlarge"):
        setattr(panel, name, _element())
    panel.latent_strip.visible = panel.agent_image.visible = True
    # What this test is not about: the demonstration list, the policy line, plan and rollout jobs.
    panel._fill_demos = panel._show_policy = panel._refresh_plan_job = panel._refresh_rollout = lambda: None

    def no_policy(*_):
        raise ValueError("no policy")  # the panel then shows 10 frames

    panel.policy_for = no_policy
    return panel


def test_a_scripted_demonstration_made_after_a_plan_stays_announced():
    """The panel selects the new demonstration, clears the plan of the old one and says so once: the next
    refresh does not replace "stored and selected" with "Demonstration changed" (it did, within half a second,
    and under load the page never drew the first message)."""
    panel = _panel_showing_a_plan_of("e-old", "e-new")
    panel.refresh()
    announced = "Scripted demonstration `e-new` stored and selected."
    assert panel.demo.value.startswith("e-new") and panel.status.content == announced
    assert panel._frames_of == "e-new" and "e-new" in panel.expert_strip.label
    assert panel.plan_wps is None and not panel.latent_strip.visible  # the old demonstration's plan is gone
    for _ in range(3):
        panel.refresh()
    assert panel.status.content == announced
