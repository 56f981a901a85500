"""Runs, shipped policies and the active checkpoint as the Train and Imitate panels see them."""

from __future__ import annotations

import json
import pickle
import zipfile

import pytest

from studio.ui.runs import ORACLE, SCENES, RunRegistry, SceneMismatch, read_metrics


def _checkpoint(path, tasks=("pick_place/cube->red",)):
    """A checkpoint file as the studio reads it (its tasks name its scene): torch.save's zip layout, no weights."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(
            f"{path.stem}/data.pkl", pickle.dumps({"format": "osvi-wm-checkpoint/1", "tasks": list(tasks)})
        )
    return path


def _run(root, name, *, steps=3, best=True, end=True, tasks=("pick_place/cube->red",)):
    d = root / "runs" / name
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"tasks": list(tasks)}))
    (d / "spec.json").write_text(json.dumps({"config": "cpu"}))
    rows = [{"event": "start", "step": 0, "total_steps": steps, "time": 1.0}]
    rows += [
        {"step": s, "loss": 1.0 / s, "loss_sdtw": 0.9 / s, "loss_wm": 0.1, "lr": 1e-4}
        for s in range(1, steps + 1)
    ]
    rows += [{"step": steps, "split": "val", "val_loss_sdtw": 0.5}]
    if end:
        rows.append({"event": "end", "status": "finished", "step": steps, "time": 2.0})
    (d / "metrics.jsonl").write_text(
        "\n".join(json.dumps(r) for r in rows) + '\n{"step": 9, "lo'
    )  # torn last line
    _checkpoint(d / "last.pt", tasks)
    if best:
        _checkpoint(d / "best.pt", tasks)
    return d


def test_runs_checkpoints_and_curves(tmp_path):
    _run(tmp_path, "train-a")
    _run(tmp_path, "train-b", best=False, end=False)
    reg = RunRegistry(tmp_path, policy_dir=tmp_path / "no-policies")
    runs = {r.id: r for r in reg.runs()}
    assert runs["train-a"].ended == "finished" and runs["train-a"].step == 3 and runs["train-a"].total == 3
    assert runs["train-a"].best_val == 0.5 and runs["train-a"].config == "cpu"
    assert runs["train-b"].ended is None and [c.id for c in runs["train-b"].checkpoints] == ["train-b/last"]
    ids = [c.id for c in reg.checkpoints()]
    assert ids == ["train-b/last", "train-a/best", "train-a/last", ORACLE], "newest run first, oracle last"
    curves = read_metrics(tmp_path / "runs" / "train-a")
    assert curves["step"].tolist() == [1, 2, 3] and curves["loss_sdtw"][0] == pytest.approx(0.9)
    assert curves["val_step"].tolist() == [3]


def test_active_checkpoint_defaults_persists_and_falls_back(tmp_path):
    policies = tmp_path / "policies"
    reg = RunRegistry(tmp_path / "data", policy_dir=policies)
    assert reg.active("pick_place").is_oracle, (
        "nothing trained, nothing shipped: the oracle, labelled as the ceiling"
    )
    _checkpoint(policies / "osvi-pick-place.pt")
    (policies / "osvi-pick-place.decoder.pt").write_bytes(b"x")  # its latent decoder is not a policy
    assert [c.id for c in reg.default_policies()] == ["default/osvi-pick-place"]
    assert reg.active("pick_place").id == "default/osvi-pick-place", (
        "a shipped policy is active from the start"
    )
    assert reg.active("pick_place").label == "shipped policy osvi-pick-place"
    (policies / "osvi-pick-place.json").write_text(
        '{"summary": "3 % held-out success"}'
    )  # its measured results
    assert reg.active("pick_place").label == "shipped policy osvi-pick-place", (
        "the summary stays out of lists"
    )
    assert reg.active("pick_place").summary == "3 % held-out success"
    _run(tmp_path / "data", "train-a")
    reg.set_active("train-a/best")
    again = RunRegistry(tmp_path / "data", policy_dir=policies)
    assert again.active("pick_place").id == "train-a/best", "survives restarts"
    (tmp_path / "data" / "runs" / "train-a" / "best.pt").unlink()
    assert reg.active("pick_place").id == "default/osvi-pick-place", (
        "a vanished checkpoint falls back to the default"
    )
    with pytest.raises(KeyError, match="no checkpoint"):
        reg.set_active("train-zzz/best")


def test_each_scene_has_its_own_active_policy(tmp_path):
    """A task is planned by its scene's policy: the choice made for that scene, else the scene's shipped policy,
    else the oracle. Choosing for one scene leaves the others alone."""
    policies = tmp_path / "policies"
    _checkpoint(policies / "pick-place-cpu.pt")
    _checkpoint(policies / "push-cpu.pt", ["push/red-forward", "push/blue-forward"])
    data = tmp_path / "data"
    _run(data, "train-pp")
    _run(data, "train-push", tasks=["push/red-forward"])
    reg = RunRegistry(data, policy_dir=policies)
    shipped = {c.id: c.scene for c in reg.default_policies()}
    assert shipped == {"default/pick-place-cpu": "pick_place", "default/push-cpu": "push"}, (
        "read from each file"
    )
    ck = {c.id: c for c in reg.checkpoints()}
    assert ck["train-push/best"].scene == "push" and "(push)" in ck["train-push/best"].label
    # Shipped fallback, per scene; no shipped Meta-World policy: the oracle.
    assert reg.active("pick_place").id == "default/pick-place-cpu"
    assert reg.active("push").id == "default/push-cpu"
    assert reg.active("metaworld").is_oracle
    # A choice counts for its scene only (by default the scene the checkpoint was trained on).
    assert reg.set_active("train-push/best").id == "train-push/best"
    assert reg.active("push").id == "train-push/best"
    assert reg.active("pick_place").id == "default/pick-place-cpu"
    reg.set_active(ORACLE, "pick_place")
    assert reg.active("pick_place").is_oracle and reg.active("push").id == "train-push/best"
    assert reg.chosen_ids() == {"push": "train-push/best", "pick_place": ORACLE}
    stored = json.loads((data / "ui" / "active_checkpoint.json").read_text())
    assert stored["scenes"] == reg.chosen_ids() and stored["id"] == ORACLE, (
        "the latest choice for older studios"
    )
    # The oracle without a scene: every scene (what one choice for everything meant before).
    reg.set_active(ORACLE)
    assert all(reg.active(s).is_oracle for s in SCENES)
    reg.set_active("default/push-cpu", "push")
    assert reg.active("push").id == "default/push-cpu" and reg.active("pick_place").is_oracle


def test_an_active_file_from_before_per_scene_choices_is_honoured(tmp_path):
    policies = tmp_path / "policies"
    _checkpoint(policies / "pick-place-cpu.pt")
    _checkpoint(policies / "push-cpu.pt", ["push/blue-forward"])
    data = tmp_path / "data"
    _run(data, "train-pp")
    active_file = data / "ui" / "active_checkpoint.json"
    active_file.parent.mkdir(parents=True)
    reg = RunRegistry(data, policy_dir=policies)
    active_file.write_text(json.dumps({"id": "train-pp/best"}))
    assert reg.active("pick_place").id == "train-pp/best", "the old choice, for the scene it was trained on"
    assert reg.active("push").id == "default/push-cpu", "and not for another scene"
    active_file.write_text(json.dumps({"id": ORACLE}))
    assert all(reg.active(s).is_oracle for s in SCENES), "the oracle was chosen for every scene"
    active_file.write_text(json.dumps({"id": "train-pp/best"}))
    reg.set_active("default/push-cpu")  # a new choice keeps the old one, now per scene
    assert reg.chosen_ids() == {"pick_place": "train-pp/best", "push": "default/push-cpu"}
    active_file.write_text("{torn")
    assert reg.active("pick_place").id == "default/pick-place-cpu", "an unreadable file: the shipped policies"


def test_a_checkpoint_of_another_scene_is_refused_not_run(tmp_path):
    policies = tmp_path / "policies"
    _checkpoint(policies / "pick-place-cpu.pt")
    _checkpoint(policies / "push-cpu.pt", ["push/blue-forward"])
    (policies / "mystery.pt").write_bytes(b"not a checkpoint")  # says nothing about its scene
    data = tmp_path / "data"
    reg = RunRegistry(data, policy_dir=policies)
    reg.set_active("default/push-cpu", "push")
    with pytest.raises(
        SceneMismatch,
        match="`default/pick-place-cpu` was trained on pick_place tasks: it does not plan push tasks",
    ):
        reg.set_active("default/pick-place-cpu", "push")
    assert reg.active("push").id == "default/push-cpu", "the refused choice changed nothing"
    with pytest.raises(SceneMismatch, match="does not say which scene it was trained on"):
        reg.set_active("default/mystery")
    with pytest.raises(SceneMismatch, match="does not say which scene"):
        reg.set_active("default/mystery", "pick_place")
    assert reg.active("pick_place").id == "default/pick-place-cpu", (
        "a file that does not say is never a default"
    )
    # A stored pairing of another scene (a hand-edited file, or a run replaced by another scene's): refused with
    # the reason rather than run, and rather than silently replaced by another policy.
    (data / "ui" / "active_checkpoint.json").write_text(
        json.dumps({"scenes": {"push": "default/pick-place-cpu"}})
    )
    with pytest.raises(SceneMismatch, match="trained on pick_place tasks: it does not plan push tasks"):
        reg.active("push")
    assert reg.active("pick_place").id == "default/pick-place-cpu"


def test_checkpoints_are_registered_in_the_catalog_before_rollouts_refer_to_them(tmp_path):
    from studio.data.catalog import Catalog, RolloutRecord

    _run(tmp_path, "train-a")
    policies = tmp_path / "policies"
    policies.mkdir()
    _checkpoint(policies / "shipped.pt")
    reg = RunRegistry(tmp_path, policy_dir=policies)
    with Catalog(tmp_path / "catalog.sqlite") as cat:
        ck = {c.id: c for c in reg.checkpoints()}
        for cid in ("train-a/best", "default/shipped", "train-a/best"):  # registering twice is harmless
            reg.register_checkpoint(cat, ck[cid])
        reg.register_checkpoint(cat, ck[ORACLE])  # the oracle is no checkpoint
        rows = {c.id: c for c in cat.checkpoints()}
        assert set(rows) == {"train-a/best", "default/shipped"}
        assert (
            rows["train-a/best"].run_id == "train-a"
            and rows["train-a/best"].is_best
            and rows["train-a/best"].step == 3
        )
        assert {r.id: r.status for r in cat.runs()} == {"train-a": "done", "shipped": "done"}
        with cat.transaction():
            cat.add_rollout(
                RolloutRecord(
                    id="r-1", task="pick_place/cube->red", success=True, checkpoint_id="train-a/best"
                )
            )
        reg.register_run(cat, "train-b", scene="pick_place")
        assert {r.id: r.status for r in cat.runs()}["train-b"] == "queued"
