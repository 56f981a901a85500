"""Demonstration guidance: dropped demonstrations are black, per demonstration, only in training steps; a guided
plan is the null plan plus g times the demonstration's displacement of it; export-policy writes g."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model.batching import collate_pairs
from studio.model.checkpoint import load_checkpoint
from studio.model.config import ModelConfig, TrainConfig
from studio.model.guidance import demonstration_gain, demonstration_surprise, drop_demonstrations, guide
from studio.model.osvi_wm import OSVIWM
from studio.model.planner import Planner
from studio.model.policy_export import export_policy
from studio.model.train import compute_losses, train

torch.set_num_threads(1)


def test_dropping_blackens_whole_demonstrations_and_leaves_the_rest_and_the_input_alone():
    frames = torch.randint(1, 255, (6, 3, 3, 8, 8), dtype=torch.uint8)
    seen_mixed = False
    for seed in range(10):
        out, chosen = drop_demonstrations(frames, 0.5, torch.Generator().manual_seed(seed))
        seen_mixed |= bool(chosen.any()) and not bool(chosen.all())
        for u in range(6):
            assert torch.equal(out[u], torch.zeros_like(frames[u]) if chosen[u] else frames[u])
    assert seen_mixed
    assert bool((frames > 0).all())  # the input was not changed in place
    same, chosen = drop_demonstrations(frames, 0.0, torch.Generator().manual_seed(0))
    assert same is frames and not chosen.any()


def test_guide_is_the_null_rows_plus_g_times_the_demonstrations_displacement():
    demo, null = torch.tensor([1.0, -2.0]), torch.tensor([0.5, 1.0])
    assert torch.equal(guide(demo, null, 1.0), demo)
    assert torch.equal(guide(demo, null, 0.0), null)
    assert torch.allclose(guide(demo, null, 3.0), torch.tensor([2.0, -8.0]))


def test_training_steps_see_black_demonstrations_and_validation_never_does():
    run = tiny_run_config()
    data = SyntheticPairs(n_tasks=3, episodes_per_task=2)
    batch = collate_pairs([data[i] for i in (0, 1, 4, 5, 8, 9)], run.model.image_size)
    torch.manual_seed(0)
    core = OSVIWM(run.model).eval()
    seen: list[torch.Tensor] = []

    def recording(expert, agent, expert_ids, targets):
        seen.append(expert)
        return core(expert, agent, expert_ids, targets=targets)

    def black(run_, generator) -> list[bool]:
        seen.clear()
        compute_losses(recording, core, batch, run_, 5, 10, generator)
        return [bool((e == 0).all()) for e in seen[0]]

    dropping = run.with_overrides(["train.demo_dropout=0.6"])
    draws = [black(dropping, torch.Generator().manual_seed(s)) for s in range(6)]
    assert any(any(d) for d in draws) and not all(all(d) for d in draws)
    assert not any(black(run, torch.Generator().manual_seed(0)))  # off by default
    assert not any(black(dropping, None))  # validation: no generator, no dropping


def test_demo_dropout_and_guidance_are_checked():
    with pytest.raises(ValueError, match="demo_dropout must be a probability"):
        TrainConfig(demo_dropout=1.0)
    with pytest.raises(ValueError, match="guidance must be in"):
        ModelConfig(image_size=(32, 32), guidance=-1.0)


def _net(weights: dict, *settings: str) -> OSVIWM:
    """The tiny network with ``weights`` and the ``model.FIELD=VALUE`` planning ``settings``."""
    model = OSVIWM(tiny_run_config().with_overrides(list(settings)).model)
    model.load_state_dict(weights)
    return model


def _planner(guidance: float, weights: dict) -> Planner:
    return Planner(_net(weights, f"model.guidance={guidance}"))


def test_a_guided_plan_extrapolates_from_the_null_plan_through_the_demonstrations():
    torch.manual_seed(0)
    weights = OSVIWM(tiny_run_config().model).state_dict()
    sample = SyntheticPairs()[0]
    expert, agent, K = sample["expert_frames"], sample["agent_frames"][0], sample["K"]
    plans = {g: _planner(g, weights).plan(expert, agent, K, np.eye(4)) for g in (0.0, 1.0, 4.0)}
    # g = 0 is the plan from black frames; g = 1 is the demonstration alone
    black = _planner(1.0, weights).plan(np.zeros_like(np.asarray(expert)), agent, K, np.eye(4))
    assert np.allclose(plans[0.0].waypoints_cam, black.waypoints_cam, atol=1e-6)
    # a guided plan returns the null plan beside it; the demonstration alone returns none
    assert plans[1.0].null_waypoints_world is None
    for g in (0.0, 4.0):
        assert np.allclose(plans[g].null_waypoints_world, black.waypoints_world, atol=1e-6)
    assert np.allclose(plans[1.0].latent_states, plans[4.0].latent_states)  # the demonstration's trajectory

    # depth, x/z and the gripper logit are affine in the raw rows, so they extrapolate: v(4) = 4 v(1) − 3 v(0)
    def parts(p):
        cam = p.waypoints_cam.astype(np.float64)
        prob = np.clip(cam[:, 3], 1e-9, 1 - 1e-9)
        return np.stack([cam[:, 2], cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2], np.log(prob / (1 - prob))])

    v0, v1, v4 = parts(plans[0.0]), parts(plans[1.0]), parts(plans[4.0])
    assert np.abs(v1 - v0).max() > 3e-4  # the demonstration moves the plan (untrained: a little)
    assert np.abs(v4 - (4 * v1 - 3 * v0)).max() < 2e-5
    assert np.abs(v4 - v1).max() > 1e-3


def test_export_policy_writes_the_guidance_the_planner_then_uses_and_refuses_models_never_dropped(tmp_path):
    run = tiny_run_config(max_steps=2, batch_size=4, val_every=100).with_overrides(["train.demo_dropout=0.5"])
    train(run, SyntheticPairs(), None, tmp_path / "run", show_progress=False)
    export_policy(tmp_path / "run" / "last.pt", tmp_path / "g2.pt", guidance=2.0)
    written = load_checkpoint(tmp_path / "g2.pt")["config"]
    original = load_checkpoint(tmp_path / "run" / "last.pt")["config"]
    assert written["model"]["guidance"] == 2.0 and original["model"]["guidance"] == 1.0
    assert written["train"] == original["train"]
    assert Planner.load(tmp_path / "g2.pt").cfg.guidance == 2.0
    export_policy(tmp_path / "run" / "last.pt", tmp_path / "same.pt")
    assert load_checkpoint(tmp_path / "same.pt")["config"] == original
    unguided = tiny_run_config(max_steps=1, batch_size=4, val_every=100)
    train(unguided, SyntheticPairs(), None, tmp_path / "plain", show_progress=False)
    with pytest.raises(ValueError, match="trained without train"):
        export_policy(tmp_path / "plain" / "last.pt", tmp_path / "bad.pt", guidance=3.0)
    assert not (tmp_path / "bad.pt").exists()


def test_the_gain_is_the_null_predictions_error_over_the_demonstrations_on_the_demonstrations_own_frames():
    torch.manual_seed(0)
    model = OSVIWM(tiny_run_config().model).eval()
    expert = torch.as_tensor(np.asarray(SyntheticPairs()[0]["expert_frames"]))
    with torch.no_grad():
        states = model.encode(expert)
        context = model.action_model.context(states[None])
        null_context = model.action_model.context(model.encode(torch.zeros_like(expert))[None])
        gain = demonstration_gain(model, states, context, null_context)
        # N = 4 frames, M = 3: the two predicted states are compared with frames round(1/2·3) = 2 and 3
        actual = model.pool(states[[2, 3]])
        errors = [
            float((model.pool(model.rollout_from_context(c, states[:1])[1])[0] - actual).norm(dim=-1).sum())
            for c in (null_context, context)
        ]
    assert errors[0] != errors[1]
    assert gain == pytest.approx(errors[0] / errors[1], rel=1e-6)
    # the surprise is the error with the demonstration: the gain's denominator
    with torch.no_grad():
        assert demonstration_surprise(model, states, context) == pytest.approx(errors[1], rel=1e-6)
    without_wm = OSVIWM(tiny_run_config().with_overrides(["model.world_model=false"]).model)
    with pytest.raises(ValueError, match="needs the world model"):
        demonstration_gain(without_wm, states, context, null_context)
    with pytest.raises(ValueError, match="needs the world model"):
        demonstration_surprise(without_wm, states, context)


def _gated(gate: float, weights: dict) -> Planner:
    return Planner(_net(weights, "model.guidance=4.0", f"model.guidance_gate={gate}"))


def test_a_gated_policy_guides_only_demonstrations_whose_gain_reaches_the_gate(monkeypatch):
    torch.manual_seed(0)
    weights = OSVIWM(tiny_run_config().model).state_dict()
    data = SyntheticPairs()
    expert, agent, K = data[0]["expert_frames"], data[0]["agent_frames"][0], data[0]["K"]
    plain = _planner(1.0, weights).plan(expert, agent, K, np.eye(4))
    always = _planner(4.0, weights).plan(expert, agent, K, np.eye(4))
    assert plain.guidance_gain is None and not plain.guided
    gain = always.guidance_gain
    assert gain is not None and gain > 0 and always.guided
    below = _gated(gain * 1.01, weights).plan(expert, agent, K, np.eye(4))
    reached = _gated(gain * 0.99, weights).plan(expert, agent, K, np.eye(4))
    assert not below.guided and np.allclose(below.waypoints_world, plain.waypoints_world, atol=1e-6)
    assert reached.guided and np.allclose(reached.waypoints_world, always.waypoints_world, atol=1e-6)
    assert below.guidance_gain == pytest.approx(gain) and reached.guidance_gain == pytest.approx(gain)
    assert np.allclose(below.null_waypoints_world, always.null_waypoints_world, atol=1e-6)

    # the gain is the demonstration's: computed once for it, again for another demonstration
    import studio.model.planner as planner_module

    calls = []

    def counting(*args):
        calls.append(1)
        return gain

    monkeypatch.setattr(planner_module, "demonstration_gain", counting)
    gated = _gated(gain, weights)
    for frame in (agent, data[1]["agent_frames"][0], agent):
        gated.plan(expert, frame, K, np.eye(4))
    assert len(calls) == 1
    gated.plan(data[4]["expert_frames"], agent, K, np.eye(4))
    assert len(calls) == 2


def test_the_gate_is_checked_and_export_policy_writes_it(tmp_path):
    with pytest.raises(ValueError, match="guidance_gate must be"):
        ModelConfig(image_size=(32, 32), guidance_gate=-0.5)
    with pytest.raises(ValueError, match="needs the world model"):
        ModelConfig(image_size=(32, 32), guidance_gate=1.1, world_model=False)
    run = tiny_run_config(max_steps=1, batch_size=4, val_every=100).with_overrides(["train.demo_dropout=0.5"])
    train(run, SyntheticPairs(), None, tmp_path / "run", show_progress=False)
    export_policy(tmp_path / "run" / "last.pt", tmp_path / "gated.pt", guidance=5.0, guidance_gate=1.04)
    cfg = Planner.load(tmp_path / "gated.pt").cfg
    assert (cfg.guidance, cfg.guidance_gate) == (5.0, 1.04)
    with pytest.raises(ValueError, match="gate without guidance does nothing"):
        export_policy(tmp_path / "run" / "last.pt", tmp_path / "bad.pt", guidance_gate=1.04)
    assert not (tmp_path / "bad.pt").exists()


def _branch_weights(weights: dict, seed: int) -> dict:
    """``weights`` with every part but the encoder moved: another fine-tune of the same encoder."""
    g = torch.Generator().manual_seed(seed)
    return {
        k: v
        if k.startswith("encoder.") or not k.endswith((".weight", ".bias"))
        else v + 0.05 * torch.randn(v.shape, generator=g)
        for k, v in weights.items()
    }


def _own_branch_and_scene() -> tuple[dict, dict, np.ndarray, np.ndarray, np.ndarray]:
    """A policy's weights, a guided branch's on the same encoder, and a demonstration, agent frame and K."""
    torch.manual_seed(0)
    own = OSVIWM(tiny_run_config().model).state_dict()
    data = SyntheticPairs()
    return own, _branch_weights(own, 1), data[0]["expert_frames"], data[0]["agent_frames"][0], data[0]["K"]


def test_a_guided_branch_plans_the_guided_demonstrations_and_the_policys_own_weights_the_rest():
    own, branch, expert, agent, K = _own_branch_and_scene()
    branch_alone = _planner(4.0, branch).plan(expert, agent, K, np.eye(4))
    own_alone = _planner(1.0, own).plan(expert, agent, K, np.eye(4))
    own_gain = _planner(4.0, own).plan(expert, agent, K, np.eye(4)).guidance_gain
    gain = branch_alone.guidance_gain
    assert gain is not None and own_gain is not None and abs(gain - own_gain) > 1e-4

    def net(weights: dict, gate: float, guidance: float = 4.0) -> OSVIWM:
        return _net(weights, f"model.guidance={guidance}", f"model.guidance_gate={gate}")

    def two(gate: float) -> Planner:
        return Planner(net(own, gate), guided_model=net(branch, gate))

    reached = two(gain * 0.99).plan(
        expert, agent, K, np.eye(4)
    )  # the branch's gain decides, not the policy's
    assert reached.guided and reached.guidance_gain == pytest.approx(gain)
    assert np.allclose(reached.waypoints_world, branch_alone.waypoints_world, atol=1e-6)
    assert np.allclose(reached.latent_states, branch_alone.latent_states, atol=1e-6)
    assert np.allclose(reached.null_waypoints_world, branch_alone.null_waypoints_world, atol=1e-6)
    below = two(gain * 1.01).plan(expert, agent, K, np.eye(4))
    assert not below.guided and below.guidance_gain == pytest.approx(gain)
    assert np.allclose(below.waypoints_world, own_alone.waypoints_world, atol=1e-6)
    assert np.allclose(below.latent_states, own_alone.latent_states, atol=1e-6)
    own_null = _planner(4.0, own).plan(expert, agent, K, np.eye(4)).null_waypoints_world
    assert np.allclose(below.null_waypoints_world, own_null, atol=1e-6)
    assert np.abs(reached.waypoints_world - below.waypoints_world).max() > 1e-3
    # the gate is set from the branch's gains, so the planner reports those
    assert two(gain).demonstration_gain(expert) == pytest.approx(gain)

    # a branch that cannot plan beside the policy is refused
    with pytest.raises(ValueError, match="needs guidance and a gate"):
        Planner(net(own, 0.0), guided_model=net(branch, 1.1))
    with pytest.raises(ValueError, match="needs guidance and a gate"):
        Planner(net(own, 1.1, guidance=1.0), guided_model=net(branch, 1.1))
    moved = {k: v + 0.01 if k.endswith("conv1.weight") else v for k, v in branch.items()}
    with pytest.raises(ValueError, match="encoder weights differ"):
        Planner(net(own, 1.1), guided_model=net(moved, 1.1))
    wider = OSVIWM(tiny_run_config().with_overrides(["model.max_waypoints=7"]).model)
    with pytest.raises(ValueError, match=r"network differs in model\.max_waypoints"):
        Planner(net(own, 1.1), guided_model=wider)


def test_a_surprise_gate_guides_with_the_policys_own_weights_the_demonstrations_the_gate_leaves(tmp_path):
    own, branch, expert, agent, K = _own_branch_and_scene()
    own_alone = _planner(1.0, own).plan(expert, agent, K, np.eye(4))
    own_guided = _planner(4.0, own).plan(expert, agent, K, np.eye(4))
    branch_guided = _planner(4.0, branch).plan(expert, agent, K, np.eye(4))
    gain = branch_guided.guidance_gain
    assert gain is not None and own_guided.guidance_surprise is None  # no surprise gate, no surprise

    def two(gate: float, surprise_gate: float, *more: str) -> Planner:
        settings = (
            "model.guidance=4.0",
            f"model.guidance_gate={gate}",
            f"model.surprise_gate={surprise_gate}",
            *more,
        )
        return Planner(_net(own, *settings), guided_model=_net(branch, *settings))

    # the surprise is the policy's own weights', as read for the export's percentile
    surprise = two(gain * 1.01, 1.0).plan(expert, agent, K, np.eye(4)).guidance_surprise
    assert surprise is not None and surprise > 0
    assert two(gain * 1.01, 1.0).demonstration_surprise(expert) == pytest.approx(surprise)
    # below the gate, at or above the surprise gate: guided by the policy's own weights, not the branch's
    surprised = two(gain * 1.01, surprise * 0.99).plan(expert, agent, K, np.eye(4))
    assert surprised.guided and surprised.guidance_surprise == pytest.approx(surprise)
    assert np.allclose(surprised.waypoints_world, own_guided.waypoints_world, atol=1e-6)
    assert np.allclose(surprised.null_waypoints_world, own_guided.null_waypoints_world, atol=1e-6)
    assert surprised.guidance_scale == own_guided.guidance_scale == 4.0
    # ... at the surprise gate's own scale when it has one; the gate's plans keep theirs
    own_at_2 = _planner(2.0, own).plan(expert, agent, K, np.eye(4))
    at_2 = two(gain * 1.01, surprise * 0.99, "model.surprise_guidance=2").plan(expert, agent, K, np.eye(4))
    assert at_2.guided and at_2.guidance_scale == 2.0
    assert np.allclose(at_2.waypoints_world, own_at_2.waypoints_world, atol=1e-6)
    assert np.abs(at_2.waypoints_world - surprised.waypoints_world).max() > 1e-3
    gated = two(gain * 0.99, surprise * 0.99, "model.surprise_guidance=2").plan(expert, agent, K, np.eye(4))
    assert gated.guidance_scale == 4.0 and np.allclose(
        gated.waypoints_world, branch_guided.waypoints_world, atol=1e-6
    )
    # below both: the demonstration's plan alone
    calm = two(gain * 1.01, surprise * 1.01).plan(expert, agent, K, np.eye(4))
    assert not calm.guided and np.allclose(calm.waypoints_world, own_alone.waypoints_world, atol=1e-6)
    assert calm.guidance_scale is None
    # reaching the gate: the branch's, whatever the surprise
    reached = two(gain * 0.99, surprise * 0.99).plan(expert, agent, K, np.eye(4))
    assert reached.guided and np.allclose(reached.waypoints_world, branch_guided.waypoints_world, atol=1e-6)
    assert np.abs(reached.waypoints_world - surprised.waypoints_world).max() > 1e-3

    with pytest.raises(ValueError, match="surprise_gate must be"):
        ModelConfig(image_size=(32, 32), surprise_gate=-1.0)
    with pytest.raises(ValueError, match="needs the world model"):
        ModelConfig(image_size=(32, 32), surprise_gate=5.0, world_model=False)
    with pytest.raises(ValueError, match="surprise_guidance must be in"):
        ModelConfig(image_size=(32, 32), guidance=5.0, surprise_gate=7.0, surprise_guidance=11.0)
    with pytest.raises(ValueError, match="surprise_guidance without a surprise_gate"):
        ModelConfig(image_size=(32, 32), guidance=5.0, surprise_guidance=3.0)
    run = tiny_run_config(max_steps=1, batch_size=4, val_every=100).with_overrides(["train.demo_dropout=0.5"])
    train(run, SyntheticPairs(), None, tmp_path / "run", show_progress=False)
    export_policy(
        tmp_path / "run" / "last.pt", tmp_path / "p.pt", guidance=5.0, guidance_gate=1.04, surprise_gate=7.5
    )
    assert Planner.load(tmp_path / "p.pt").cfg.surprise_gate == 7.5
    # a later re-export sets the surprise gate's own scale and keeps the rest
    export_policy(tmp_path / "p.pt", tmp_path / "p3.pt", surprise_guidance=3.0)
    cfg = Planner.load(tmp_path / "p3.pt").cfg
    assert (cfg.guidance, cfg.surprise_gate, cfg.surprise_scale) == (5.0, 7.5, 3.0)
    with pytest.raises(ValueError, match="surprise gate without guidance does nothing"):
        export_policy(tmp_path / "run" / "last.pt", tmp_path / "bad.pt", surprise_gate=7.5)
    assert not (tmp_path / "bad.pt").exists()
