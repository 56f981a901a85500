"""The full network: shapes at several resolutions, ablations, shared experts, targets and stop-gradient."""

from __future__ import annotations

import pytest
import torch

from studio.model.config import ModelConfig
from studio.model.osvi_wm import OSVIWM, waypoint_set

torch.set_num_threads(1)


def tiny(**kw) -> ModelConfig:
    base = dict(
        image_size=(48, 64),
        n_expert_frames=3,
        n_agent_frames=4,
        encoder_stages=2,
        state_channels=8,
        action_blocks=1,
        action_heads=2,
        action_attn_dim=8,
        action_mlp_dim=16,
        wm_width=16,
        wm_heads=2,
        wm_mlp_dim=32,
        head_hidden=32,
        head_dropout=0.0,
    )
    base.update(kw)
    return ModelConfig(**base)


def frames(b: int, t: int, size, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (b, t, 3, *size), generator=g, dtype=torch.uint8)


@pytest.mark.parametrize(
    ("size", "stages", "grid"), [((48, 64), 2, (6, 8)), ((64, 96), 3, (4, 6)), ((96, 72), 2, (12, 9))]
)
def test_shapes_follow_config_and_resolution(size, stages, grid):
    torch.manual_seed(0)
    model = OSVIWM(tiny(image_size=size, encoder_stages=stages))
    assert model.map_shape == (8, *grid)
    out = model(frames(2, 3, size), frames(2, 4, size), targets="detached")
    assert out.waypoints.shape == (2, 15, 4)
    assert out.states.shape == (2, 3, 8, *grid) and out.actions.shape == (2, 3, 8, *grid)
    assert out.pooled.shape == out.target_pooled.shape == (2, 3, 16)
    assert waypoint_set(out.waypoints, 5).shape == (2, 5, 4)


@pytest.mark.parametrize(
    ("switch", "steps", "state_shape"),
    [
        ({"world_model": False}, 1, (8, 6, 8)),
        ({"pool_before_wm": True}, 3, (16,)),
        ({"single_step": True}, 1, (8, 6, 8)),
    ],
)
def test_ablations_change_the_rollout(switch, steps, state_shape):
    torch.manual_seed(0)
    model = OSVIWM(tiny(**switch))
    out = model(frames(2, 3, (48, 64)), frames(2, 4, (48, 64)), targets="detached")
    assert model.state_shape == state_shape
    assert out.states.shape == (2, steps, *state_shape)
    if switch.get("world_model") is False:
        assert model.world_model is None and out.target_pooled is None
    else:
        assert out.target_pooled.shape == (2, steps, 16)
    if switch.get("single_step"):
        assert model.target_frame_indices() == [3]


def test_a_shared_expert_gives_the_same_plan_as_duplicated_experts():
    torch.manual_seed(0)
    model = OSVIWM(tiny()).eval()
    expert = frames(1, 3, (48, 64))
    agent = frames(3, 4, (48, 64), seed=1)
    with torch.no_grad():
        shared = model(expert, agent, torch.zeros(3, dtype=torch.long))
        dup = model(expert.expand(3, -1, -1, -1, -1), agent)
    assert torch.allclose(shared.waypoints, dup.waypoints, atol=1e-5)


def test_future_agent_frames_only_feed_targets():
    torch.manual_seed(0)
    model = OSVIWM(tiny()).eval()
    expert, agent = frames(2, 3, (48, 64)), frames(2, 4, (48, 64), seed=1)
    changed = agent.clone()
    changed[:, 1:] = frames(2, 3, (48, 64), seed=2)
    with torch.no_grad():
        a = model(expert, agent, targets="detached")
        b = model(expert, changed, targets="detached")
    assert torch.equal(a.waypoints, b.waypoints) and torch.equal(a.states, b.states)
    assert not torch.allclose(a.target_pooled, b.target_pooled)


@pytest.mark.parametrize(("mode", "flows"), [("detached", False), ("grad", True)])
def test_stop_gradient_really_stops_gradients(mode, flows):
    torch.manual_seed(0)
    model = OSVIWM(tiny())
    expert = frames(2, 3, (48, 64)).float() / 255
    agent = (frames(2, 4, (48, 64), seed=1).float() / 255).requires_grad_(True)
    out = model(expert, agent, targets=mode)
    wm_loss = (out.pooled - out.target_pooled).abs().mean()
    (grad,) = torch.autograd.grad(wm_loss, agent)
    future_grad = grad[:, 1:].abs().sum()
    assert (future_grad > 0) == flows
    assert grad[:, 0].abs().sum() > 0  # the input frame always receives gradient through the prediction


def test_decode_waypoints_uses_the_given_intrinsics_and_depth_prior():
    model = OSVIWM(tiny())
    model.set_depth_prior(1.5)
    raw = torch.zeros(1, 15, 4)
    raw[0, :, :2] = 0.5  # right-bottom quadrant, depth 1.5
    K = torch.tensor([[[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]]])
    dec = model.decode_waypoints(raw, K)
    expected = torch.tensor([(48 - 32) / 40 * 1.5, (36 - 24) / 40 * 1.5, 1.5])
    assert torch.allclose(dec["position"][0, 0], expected, atol=1e-6)
    assert torch.allclose(dec["gripper"], torch.full((1, 15), 0.5))


def test_wrong_input_size_is_rejected():
    model = OSVIWM(tiny())
    with pytest.raises(ValueError, match="frames must be"):
        model(frames(1, 3, (32, 32)), frames(1, 4, (32, 32)))


def test_the_demonstration_task_head_reads_expert_frames_only_and_leaves_the_plan_unchanged():
    torch.manual_seed(0)
    plain = OSVIWM(tiny()).eval()
    torch.manual_seed(0)
    model = OSVIWM(tiny(demo_task_classes=5)).eval()
    assert plain(frames(2, 3, (48, 64)), frames(2, 4, (48, 64), seed=1)).demo_task_logits is None
    missing = set(model.state_dict()) - set(plain.state_dict())
    assert missing and all(k.startswith("demo_task_head.") for k in missing)
    model.load_state_dict({**model.state_dict(), **plain.state_dict()})
    expert = frames(2, 3, (48, 64))
    agent = frames(4, 4, (48, 64), seed=1)
    ids = torch.tensor([0, 1, 1, 0])
    with torch.no_grad():
        out = model(expert, agent, ids)
        ref = plain(expert, agent, ids)
        other_agent = model(expert, frames(4, 4, (48, 64), seed=2), ids)
    assert out.demo_task_logits.shape == (2, 5)  # one row per expert video, not per pair
    assert torch.equal(out.waypoints, ref.waypoints)  # the head only adds an output
    assert torch.equal(out.demo_task_logits, other_agent.demo_task_logits)  # and sees the expert frames only
    model.train()
    loss = torch.nn.functional.cross_entropy(model(expert, agent, ids).demo_task_logits, torch.tensor([3, 1]))
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.action_model.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())
    assert all(p.grad is None for p in model.head.parameters())  # the waypoint head is not involved
