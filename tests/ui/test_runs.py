"""Runs, shipped policies and the active checkpoint as the Train and Imitate panels see them."""

from __future__ import annotations

import json

import pytest

from studio.ui.runs import ORACLE, RunRegistry, read_metrics


def _run(root, name, *, steps=3, best=True, end=True):
    d = root / "runs" / name
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"tasks": ["pick_place/cube->red"]}))
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
    (d / "last.pt").write_bytes(b"x")
    if best:
        (d / "best.pt").write_bytes(b"x")
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
    assert reg.active().is_oracle, "nothing trained, nothing shipped: the oracle, labelled as the ceiling"
    policies.mkdir()
    (policies / "osvi-pick-place.pt").write_bytes(b"x")
    (policies / "osvi-pick-place.decoder.pt").write_bytes(b"x")  # its latent decoder is not a policy
    assert [c.id for c in reg.default_policies()] == ["default/osvi-pick-place"]
    assert reg.active().id == "default/osvi-pick-place", "a shipped policy is active from the start"
    assert reg.active().label == "shipped policy osvi-pick-place"
    (policies / "osvi-pick-place.json").write_text(
        '{"summary": "3 % held-out success"}'
    )  # its measured results
    assert reg.active().label == "shipped policy osvi-pick-place — 3 % held-out success"
    assert reg.active().summary == "3 % held-out success"
    _run(tmp_path / "data", "train-a")
    reg.set_active("train-a/best")
    assert (
        RunRegistry(tmp_path / "data", policy_dir=policies).active().id == "train-a/best"
    )  # survives restarts
    (tmp_path / "data" / "runs" / "train-a" / "best.pt").unlink()
    assert reg.active().id == "default/osvi-pick-place", "a vanished checkpoint falls back to the default"
    with pytest.raises(KeyError, match="no checkpoint"):
        reg.set_active("train-zzz/best")


def test_checkpoints_are_registered_in_the_catalog_before_rollouts_refer_to_them(tmp_path):
    from studio.data.catalog import Catalog, RolloutRecord

    _run(tmp_path, "train-a")
    policies = tmp_path / "policies"
    policies.mkdir()
    (policies / "shipped.pt").write_bytes(b"x")
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
