"""Pure helpers of the panels: dataset counts, override parsing, task labels, a compared rollout's stage, the Train
tab's loss curves."""

from types import SimpleNamespace

import numpy as np

from studio.ui.panels.compare import OpenedRollout, task_choices
from studio.ui.panels.datasets import counts_table
from studio.ui.panels.imitate import HELD_OUT, ImitatePanel, task_labels
from studio.ui.panels.train import parse_overrides


def test_counts_table_by_role_and_source():
    meta = lambda task, role, source: SimpleNamespace(task=task, role=role, source=source)  # noqa: E731
    metas = [meta("pick_place/cube->red", "expert", "scripted")] * 3 + [
        meta("pick_place/cube->red", "expert", "upload"),
        meta("pick_place/cube->red", "agent", "rollout"),
        meta("push/red-forward", "agent", "teleop"),
    ]
    text = counts_table(metas)
    assert "| pick_place/cube->red | 3 scripted, 1 upload | 1 rollout |" in text
    assert "| push/red-forward | — | 1 teleop |" in text and "6 episodes: 4 expert, 2 agent." in text
    assert "empty" in counts_table([])


def test_parse_overrides_keeps_lists_together():
    text = "model.image_size=[48, 64]; train.batch_size=4;\n train.log_every=1 ;"
    assert parse_overrides(text) == ["model.image_size=[48, 64]", "train.batch_size=4", "train.log_every=1"]


def test_task_labels_mark_the_held_out_tasks():
    labels = task_labels()
    assert labels["pick_place/bar->blue" + HELD_OUT] == "pick_place/bar->blue"
    assert labels["pick_place/cube->red"] == "pick_place/cube->red"
    assert labels["push/blue-backward" + HELD_OUT] == "push/blue-backward"
    assert list(labels).index("pick_place/bar->blue" + HELD_OUT) < list(labels).index("pick_place/cube->red")


def test_choosing_a_meta_world_task_sets_the_papers_re_plans_and_says_the_bound():
    """Meta-World's held-out tasks get the paper's protocol in the Imitate tab: 3 re-plans on the hard ones, none on
    the easy ones, each plan bounded at 500 control ticks, said under *Re-plans*; elsewhere the person's choice
    stays and nothing is said (a Meta-World training task: only the bound)."""
    panel = SimpleNamespace(
        task_name="", replans=SimpleNamespace(value=2), protocol_note=SimpleNamespace(content=""), _shown={}
    )

    def choose(task: str) -> tuple[int, str]:
        panel.task_name = task
        ImitatePanel._apply_protocol(panel)
        return panel.replans.value, panel.protocol_note.content

    replans, note = choose("metaworld/door-unlock-v3")
    assert replans == 3 and "3 re-plans; each plan executes at most 500 control ticks" in note
    replans, note = choose("metaworld/button-press-v3")
    assert replans == 0 and "one attempt, no re-plans; each plan executes at most 500 control ticks" in note
    panel.replans.value = 2
    replans, note = choose("metaworld/assembly-v3")
    assert replans == 2 and note.startswith("*Each plan executes at most 500 control ticks")
    replans, note = choose("pick_place/bar->blue")
    assert replans == 2 and note == ""


def test_the_imitate_policy_line_names_the_policy_of_the_tasks_scene(tmp_path):
    import json
    import pickle
    import zipfile

    from studio.ui.panels.imitate import ImitatePanel
    from studio.ui.runs import RunRegistry

    policies = tmp_path / "policies"
    policies.mkdir()
    for name, task in (("pick-place-cpu", "pick_place/cube->red"), ("push-cpu", "push/red-forward")):
        with zipfile.ZipFile(policies / f"{name}.pt", "w") as zf:  # torch.save's layout, metadata only
            zf.writestr(f"{name}/data.pkl", pickle.dumps({"tasks": [task]}))
    (policies / "push-cpu.json").write_text('{"summary": "99 % on the unseen push task"}')
    reg = RunRegistry(tmp_path / "data", policy_dir=policies)
    panel = SimpleNamespace(app=SimpleNamespace(runs=reg))
    panel.policy_for = lambda task, who=None: ImitatePanel.policy_for(panel, task, who)
    line = lambda task: ImitatePanel.policy_text(panel, task)  # noqa: E731
    # The line names the policy; what was measured with it is in the fold under it.
    assert line("push/blue-backward") == "Policy for **push** tasks: `default/push-cpu`"
    assert ImitatePanel.policy_about(panel, "push/blue-backward").startswith("99 % on the unseen push task")
    assert line("pick_place/bar->blue") == "Policy for **pick_place** tasks: `default/pick-place-cpu`"
    assert "**oracle — execution ceiling**" in line("metaworld/door-unlock-v3")
    assert "no policy for metaworld is shipped or chosen" in line("metaworld/door-unlock-v3")
    reg.set_active("oracle", "push")
    assert "**oracle — execution ceiling**" in line("push/blue-backward") and "chosen in Train" in line(
        "push/x"
    )
    active = tmp_path / "data" / "ui" / "active_checkpoint.json"
    active.write_text(json.dumps({"scenes": {"push": "default/pick-place-cpu"}}))
    assert line("push/blue-backward").startswith(
        "Policy for **push** tasks: ✘ `default/pick-place-cpu` was trained on pick_place tasks: it does not plan "
        "push tasks"
    )
    assert line("push/blue-backward").endswith("Plan and Execute refuse to run it.")


def test_a_demonstration_is_imitated_by_the_shipped_policy_that_learnt_from_its_demonstrator(tmp_path):
    import json
    import pickle
    import zipfile

    from studio.ui.panels.imitate import ImitatePanel
    from studio.ui.runs import RunRegistry

    policies = tmp_path / "policies"
    policies.mkdir()
    shipped = {  # name: (demonstrators in the file's configuration, in its NAME.json)
        "push-cpu": ((), ["sawyer"]),
        "push-human-demos": (("human",), None),
        "push-panda-demos": (("panda",), None),
    }
    for name, (configured, listed) in shipped.items():
        info = {"tasks": ["push/red-forward"], "config": {"train": {"expert_embodiments": configured}}}
        with zipfile.ZipFile(policies / f"{name}.pt", "w") as zf:
            zf.writestr(f"{name}/data.pkl", pickle.dumps(info))
        if listed is not None:
            (policies / f"{name}.json").write_text(json.dumps({"summary": "", "demonstrators": listed}))
    reg = RunRegistry(tmp_path / "data", policy_dir=policies)
    by_id = {c.id: c.demonstrators for c in reg.default_policies()}
    assert by_id == {
        "default/push-cpu": ("sawyer",),
        "default/push-human-demos": ("human",),
        "default/push-panda-demos": ("panda",),
    }
    demo = SimpleNamespace(value="(none)")
    panel = SimpleNamespace(app=SimpleNamespace(runs=reg), demo=demo)
    panel.demonstrator = lambda: ImitatePanel.demonstrator(panel)
    panel.policy_for = lambda task, who=None: ImitatePanel.policy_for(panel, task, who)
    chosen = {}
    for value in ("(none)", "e1 · upload · human", "e2 · scripted · panda", "e3 · teleop · sawyer"):
        demo.value = value
        chosen[panel.demonstrator()] = panel.policy_for("push/blue-backward", panel.demonstrator()).id
    assert chosen == {
        None: "default/push-cpu",
        "human": "default/push-human-demos",
        "panda": "default/push-panda-demos",
        "sawyer": "default/push-cpu",
    }
    demo.value = "e1 · upload · human"
    assert ImitatePanel.policy_text(panel, "push/x", "human") == (
        "Policy for **push** tasks: `default/push-human-demos` (learnt from human demonstrations, like this one)"
    )
    # No shipped policy learnt from Meta-World's demonstrator here: the scene's first is used, unchanged.
    assert reg.active("push", "nobody").id == "default/push-cpu"
    # The user's choice for the scene wins over the demonstrator.
    reg.set_active("default/push-panda-demos", "push")
    assert reg.active("push", "human").id == "default/push-panda-demos"
    assert "(chosen in Train)" in ImitatePanel.policy_text(panel, "push/x", "human")


def test_a_forked_episode_says_where_it_came_from():
    from studio.ui.panels.datasets import forked_note

    note = forked_note({"forked_from": {"rollout": "r-1", "step": 40, "episode": "e"}, "worker": "w"})
    assert "rollout `r-1` at step 40" in note and "first 41 steps" in note
    assert (
        forked_note({"worker": "w"}) == ""
        and forked_note(None) == ""
        and forked_note({"forked_from": 3}) == ""
    )


def test_a_compared_rollout_says_what_it_does_at_each_step_and_holds_its_end():
    record = SimpleNamespace(
        success=False,
        failure_stage="place",
        extra={"stage_ticks": {"reached": 40, "grasped": 60, "placed": None}},
    )
    replay = SimpleNamespace(num_steps=100, frame_steps=np.array([0, 50, 99]))
    frames = np.arange(3).reshape(3, 1, 1, 1) * np.ones((3, 2, 2, 3), np.uint8)
    side = OpenedRollout("A", "ck", record, replay, frames, np.array([0, 70]))
    assert [side.short(s) for s in (0, 40, 59, 60, 99, 150)] == [
        "reaching",
        "grasping",
        "grasping",
        "placing",
        "ended: failed at place",
        "ended: failed at place",
    ]
    assert side.describe(10) == "reaching, plan 1 of 2" and side.describe(80) == "placing, plan 2 of 2"
    assert side.describe(99) == "ended at step 99: ✘ failed at place"
    assert side.describe(120) == "ended at step 99: ✘ failed at place (holding its last frame)"
    assert [int(side.frame_at(s)[0, 0, 0]) for s in (0, 49, 50, 98, 99, 500)] == [0, 0, 1, 1, 2, 2]
    record.extra = {}
    assert side.describe(10) == "stage timing not recorded, plan 1 of 2"
    assert task_choices("push")[:3] == ("held-out", "train", "all") and "push/blue-backward" in task_choices(
        "push"
    )


def test_loss_curves_from_progress_messages_give_way_to_the_metrics_file_at_the_same_step(tmp_path):
    """The Train tab first draws the total loss from the job's progress messages; once ``metrics.jsonl`` holds the
    same steps, its separate losses must replace them (they stayed blank when the step count matched)."""
    import json

    from studio.ui.panels.train import TrainPanel

    plot = lambda: SimpleNamespace(data=None, scales=None)  # noqa: E731
    panel = SimpleNamespace(_shown={}, loss_plot=plot(), lr_plot=plot())
    history = [SimpleNamespace(step=s, metrics={"loss": 1.0 / s, "lr": 1e-4}) for s in range(1, 5)]
    tracked = SimpleNamespace(spec={"run_dir": str(tmp_path)}, history=history)
    TrainPanel._show_curves(panel, tracked)
    assert panel.loss_plot.data[0][-1] == 4 and not np.isfinite(panel.loss_plot.data[2]).any()
    rows = [
        {"step": s, "loss": 1.0 / s, "loss_sdtw": 0.5 / s, "loss_wm": 0.1, "lr": 1e-4} for s in range(1, 5)
    ]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    TrainPanel._show_curves(panel, tracked)
    assert panel.loss_plot.data[0][-1] == 4 and np.isfinite(panel.loss_plot.data[2]).all()
    assert np.allclose(panel.loss_plot.data[3], 0.1)
