"""Policy export: a small float16 inference file that plans like its training checkpoint, decoder alongside."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.cli import main
from studio.eval.latents import find_decoder
from studio.model.checkpoint import GUIDED_WEIGHTS, load_checkpoint
from studio.model.config import DecoderConfig
from studio.model.planner import Planner
from studio.model.policy_export import export_policy
from studio.model.train import train
from studio.model.train_decoder import load_decoder, train_decoder

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    train(
        tiny_run_config(max_steps=3, batch_size=4, val_every=100),
        SyntheticPairs(),
        None,
        out,
        show_progress=False,
    )
    cfg = DecoderConfig(
        base_channels=16, stages=3, batch_size=4, steps=2, val_every=100, log_every=1, num_workers=0
    )
    train_decoder(out / "last.pt", SyntheticPairs(), None, out / "decoder", cfg, show_progress=False)
    return out


def test_exported_policy_plans_like_the_checkpoint_at_a_fraction_of_the_size(trained, tmp_path):
    src = trained / "last.pt"
    sizes = export_policy(src, tmp_path / "policy.pt", decoder=trained / "decoder" / "last.pt")
    assert sizes["policy_bytes"] < 0.25 * src.stat().st_size  # no optimiser state, half-precision weights
    policy = load_checkpoint(tmp_path / "policy.pt")
    assert (
        "optimizer" not in policy
        and policy["step"] == 3
        and policy["config"] == load_checkpoint(src)["config"]
    )
    sample = SyntheticPairs()[0]
    args = (sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4))
    full, small = Planner.load(src).plan(*args), Planner.load(tmp_path / "policy.pt").plan(*args)
    assert np.abs(full.waypoints_cam[:, :3] - small.waypoints_cam[:, :3]).max() < 1e-3  # metres
    assert next(Planner.load(tmp_path / "policy.pt").model.parameters()).dtype == torch.float32
    # The decoder sits where the studio looks for it, and renders the exported model's latents.
    dec_path = find_decoder(tmp_path / "policy.pt")
    assert dec_path == tmp_path / "policy.decoder.pt"
    images = load_decoder(dec_path).render(small.pooled_states.astype(np.float32))
    assert images.dtype == np.uint8 and images.shape[0] == small.pooled_states.shape[0]


def test_export_command_reports_bad_input(trained, tmp_path, capsys):
    assert main(["export-policy", str(tmp_path / "nope.pt"), str(tmp_path / "p.pt")]) == 2
    assert "nope.pt" in capsys.readouterr().err
    assert (
        main(
            [
                "export-policy",
                str(trained / "last.pt"),
                str(tmp_path / "p.pt"),
                "--decoder",
                str(trained / "last.pt"),
            ]
        )
        == 2
    )
    assert "not a latent-decoder checkpoint" in capsys.readouterr().err
    assert main(["export-policy", str(trained / "last.pt"), str(tmp_path / "q.pt")]) == 0
    assert "policy_bytes=" in capsys.readouterr().out


def test_the_gate_percentile_is_read_off_the_training_tasks_stored_demonstrations(tmp_path):
    from studio.data.collect import CollectConfig, collect
    from studio.data.store import EpisodeStore
    from studio.model.policy_export import (
        gate_from_training_demonstrations,
        surprise_gate_from_training_demonstrations,
    )

    run = tiny_run_config(max_steps=1, batch_size=4, val_every=100).with_overrides(["train.demo_dropout=0.5"])
    train(run, SyntheticPairs(), None, tmp_path / "run", show_progress=False)
    ckpt = load_checkpoint(tmp_path / "run" / "last.pt")
    ckpt["tasks"] = [
        "pick_place/bar->blue"
    ]  # as if trained on it, so its demonstrations are the training ones
    named = tmp_path / "named.pt"
    torch.save(ckpt, named)
    data = tmp_path / "data"
    collect(
        CollectConfig(
            scene="pick_place",
            robot="sawyer",
            tasks=["pick_place/bar->blue", "pick_place/bar->red"],
            episodes=2,
            data_dir=str(data),
            progress=False,
            image_size=(48, 64),
        )
    )
    planner = Planner.load(named)
    with EpisodeStore(data) as store:
        training = store.episodes(role="expert", task="pick_place/bar->blue")
        gains = [planner.demonstration_gain(store.load_frames(m.id)) for m in training]
    assert len(gains) == 2 and gains[0] != gains[1]
    gate, n = gate_from_training_demonstrations(named, data, 50)
    assert n == 2 and gate == pytest.approx(float(np.mean(gains)))  # bar->red's demonstrations are not read
    args = [str(named), str(tmp_path / "gated.pt"), "--guidance", "5", "--gate-percentile", "100"]
    assert main(["export-policy", *args, "--data", str(data)]) == 0
    assert Planner.load(tmp_path / "gated.pt").cfg.guidance_gate == pytest.approx(max(gains))
    assert main(["export-policy", *args]) == 2  # no --data
    # with a guided branch the gate is read off the branch's gains, which are the ones it is compared with
    g = torch.Generator().manual_seed(1)
    own = dict(ckpt)
    own["model"] = {
        k: v + 0.05 * torch.randn(v.shape, generator=g)
        if k.startswith("world_model.") and k.endswith("weight")
        else v
        for k, v in ckpt["model"].items()
    }
    torch.save(own, tmp_path / "own.pt")
    two = [str(tmp_path / "own.pt"), str(tmp_path / "two.pt"), "--guidance", "5", "--gate-percentile", "100"]
    assert main(["export-policy", *two, "--data", str(data), "--guided-from", str(named)]) == 0
    assert Planner.load(tmp_path / "two.pt").cfg.guidance_gate == pytest.approx(max(gains))
    assert gate_from_training_demonstrations(tmp_path / "own.pt", data, 100)[0] != pytest.approx(max(gains))
    with pytest.raises(ValueError, match="percentile must be"):
        gate_from_training_demonstrations(named, data, 0)
    # the surprise gate: the same percentile of the training demonstrations' surprises, read by the policy's own
    # weights (not the branch's)
    mine = Planner.load(tmp_path / "own.pt")
    with EpisodeStore(data) as store:
        surprises = [mine.demonstration_surprise(store.load_frames(m.id)) for m in training]
    assert surprise_gate_from_training_demonstrations(tmp_path / "own.pt", data, 50) == (
        pytest.approx(float(np.mean(surprises))),
        2,
    )
    three = [*two[:2], "--guidance", "5", "--gate-percentile", "100", "--surprise-percentile", "100"]
    assert main(["export-policy", *three, "--data", str(data), "--guided-from", str(named)]) == 0
    assert Planner.load(tmp_path / "two.pt").cfg.surprise_gate == pytest.approx(max(surprises))
    assert main(["export-policy", *three, "--surprise-gate", "3", "--data", str(data)]) == 2
    # the surprise gate's own scale, set by a later re-export that keeps the gates and the branch
    scaled = [str(tmp_path / "two.pt"), str(tmp_path / "scaled.pt"), "--surprise-guidance", "3"]
    assert main(["export-policy", *scaled]) == 0
    cfg = Planner.load(tmp_path / "scaled.pt").cfg
    assert (cfg.guidance, cfg.surprise_scale) == (5.0, 3.0)
    assert cfg.surprise_gate == pytest.approx(max(surprises))
    assert load_checkpoint(tmp_path / "scaled.pt").get(GUIDED_WEIGHTS) is not None
    # ... and refused without a surprise gate to scale
    assert (
        main(
            [
                "export-policy",
                str(tmp_path / "own.pt"),
                str(tmp_path / "bad.pt"),
                *two[2:4],
                "--surprise-guidance",
                "3",
            ]
        )
        == 2
    )
    assert not (tmp_path / "bad.pt").exists()
    ckpt["tasks"] = ["pick_place/bar->yellow"]
    torch.save(ckpt, named)
    with pytest.raises(ValueError, match="no expert demonstration"):
        gate_from_training_demonstrations(named, data, 95)


def test_a_guided_branch_is_written_without_its_encoder_and_planned_by_the_loaded_policy(tmp_path):
    from studio.model.checkpoint import guided_model_from_checkpoint, model_from_checkpoint

    dropped = tiny_run_config(max_steps=2, batch_size=4, val_every=100).with_overrides(
        ["train.demo_dropout=0.5"]
    )
    train(dropped, SyntheticPairs(), None, tmp_path / "guide", show_progress=False)
    # the next stage: the same encoder, fixed; the other parts trained on
    fixed = dropped.with_overrides(["train.freeze=encoder", "train.lr_max=1e-2"])
    train(
        fixed,
        SyntheticPairs(),
        None,
        tmp_path / "end",
        show_progress=False,
        init=tmp_path / "guide" / "last.pt",
    )
    end, guide = tmp_path / "end" / "last.pt", tmp_path / "guide" / "last.pt"
    export_policy(end, tmp_path / "two.pt", guidance=4.0, guidance_gate=1e-6, guided_from=guide)
    policy = load_checkpoint(tmp_path / "two.pt")
    assert policy["guided_from"] == str(guide)
    assert policy[GUIDED_WEIGHTS] and not any(k.startswith("encoder.") for k in policy[GUIDED_WEIGHTS])
    branch = guided_model_from_checkpoint(policy)
    expected = model_from_checkpoint(load_checkpoint(guide)).state_dict()
    assert branch is not None and all(
        torch.allclose(v, expected[k], atol=1e-2) for k, v in branch.state_dict().items()
    )  # float16-stored
    sample = SyntheticPairs()[0]
    args = (sample["expert_frames"], sample["agent_frames"][0], sample["K"], np.eye(4))
    planner = Planner.load(tmp_path / "two.pt")
    assert planner.guided_model is not None
    plan = planner.plan(*args)  # a gate this low guides every demonstration: the branch plans
    export_policy(guide, tmp_path / "guide.pt", guidance=4.0)
    alone = Planner.load(tmp_path / "guide.pt").plan(*args)
    assert plan.guided and np.abs(plan.waypoints_world - alone.waypoints_world).max() < 1e-5
    assert guided_model_from_checkpoint(load_checkpoint(tmp_path / "guide.pt")) is None
    # exported again, the branch is carried, and kept only with guidance and a gate
    export_policy(tmp_path / "two.pt", tmp_path / "again.pt", guidance_gate=2e-6)
    assert load_checkpoint(tmp_path / "again.pt")[GUIDED_WEIGHTS].keys() == policy[GUIDED_WEIGHTS].keys()
    with pytest.raises(ValueError, match="needs guidance and a gate"):
        export_policy(tmp_path / "two.pt", tmp_path / "bad.pt", guidance=1.0, guidance_gate=0.0)

    # refusals, and nothing written for them
    with pytest.raises(ValueError, match="needs guidance and a gate"):
        export_policy(end, tmp_path / "bad.pt", guidance=4.0, guided_from=guide)
    other = tiny_run_config(max_steps=2, batch_size=4, val_every=100, seed=3).with_overrides(
        ["train.demo_dropout=0.5"]
    )
    train(other, SyntheticPairs(), None, tmp_path / "apart", show_progress=False)
    with pytest.raises(ValueError, match="encoder weights differ"):
        export_policy(
            end,
            tmp_path / "bad.pt",
            guidance=4.0,
            guidance_gate=1.1,
            guided_from=tmp_path / "apart" / "last.pt",
        )
    with pytest.raises(ValueError, match="has a guided branch of its own"):
        export_policy(
            end, tmp_path / "bad.pt", guidance=4.0, guidance_gate=1.1, guided_from=tmp_path / "two.pt"
        )
    plain = tiny_run_config(max_steps=1, batch_size=4, val_every=100)
    train(plain, SyntheticPairs(), None, tmp_path / "plain", show_progress=False)
    with pytest.raises(ValueError, match=r"trained without train\.demo_dropout"):
        export_policy(
            end,
            tmp_path / "bad.pt",
            guidance=4.0,
            guidance_gate=1.1,
            guided_from=tmp_path / "plain" / "last.pt",
        )
    assert not (tmp_path / "bad.pt").exists()
