"""The world model 𝒲: shapes, causality and cached steps."""

from __future__ import annotations

import pytest
import torch

from studio.model.world_model import WorldModel

torch.set_num_threads(1)


@pytest.mark.parametrize(
    ("state_shape", "tokens"), [((6, 3, 5), "map"), ((10,), "map"), ((6, 3, 5), "cells")]
)
def test_steps_with_cache_equal_the_full_causal_pass(state_shape, tokens):
    torch.manual_seed(0)
    wm = WorldModel(state_shape, width=16, blocks=1, heads=4, mlp_dim=32, tokens=tokens).eval()
    states = torch.randn(2, 4, *state_shape)
    actions = torch.randn(2, 4, *state_shape)
    full = wm(states, actions)
    assert full.shape == (2, 4, *state_shape)
    cache = None
    for i in range(4):
        nxt, cache = wm.step(states[:, i], actions[:, i], cache)
        assert torch.allclose(nxt, full[:, i], atol=1e-5)


@pytest.mark.parametrize("tokens", ["map", "cells"])
def test_prediction_at_a_step_ignores_later_steps(tokens):
    torch.manual_seed(0)
    wm = WorldModel((4, 2, 3), width=16, blocks=1, heads=2, mlp_dim=16, tokens=tokens).eval()
    states, actions = torch.randn(1, 5, 4, 2, 3), torch.randn(1, 5, 4, 2, 3)
    out = wm(states, actions)
    states2 = states.clone()
    states2[:, 3:] += torch.randn(1, 2, 4, 2, 3)
    out2 = wm(states2, actions)
    assert torch.allclose(out[:, :3], out2[:, :3], atol=1e-6)
    assert not torch.allclose(out[:, 3], out2[:, 3])


def test_layer_sizes_follow_the_state_shape():
    wm = WorldModel((512, 8, 10), width=512, blocks=1, heads=4, mlp_dim=2048)
    assert wm.embed.in_features == 2 * 512 * 80 and wm.out.out_features == 512 * 80
    cells = WorldModel((64, 9, 12), width=128, blocks=1, heads=4, mlp_dim=256, tokens="cells")
    assert cells.embed.in_features == 2 * 64 and cells.out.out_features == 64
    with pytest.raises(ValueError, match="tokens"):
        WorldModel((4, 2, 3), width=16, blocks=1, heads=2, mlp_dim=16, tokens="pixels")


def test_cell_tokens_keep_an_action_at_its_cell():
    """A change of the action at one cell moves the predicted state most at that cell (per-cell 𝒲)."""
    torch.manual_seed(0)
    wm = WorldModel((4, 3, 4), width=16, blocks=1, heads=2, mlp_dim=16, tokens="cells").eval()
    states, actions = torch.randn(1, 1, 4, 3, 4), torch.randn(1, 1, 4, 3, 4)
    moved = actions.clone()
    moved[..., 1, 2] += 3.0
    change = (wm(states, moved) - wm(states, actions)).abs().sum(2)[0, 0]  # (3, 4) per cell
    assert change.argmax().item() == 1 * 4 + 2


def test_residual_world_model_starts_as_the_identity_and_learns_changes():
    torch.manual_seed(0)
    wm = WorldModel((4, 2, 3), width=16, blocks=1, heads=2, mlp_dim=16, residual=True)
    states, actions = torch.randn(2, 3, 4, 2, 3), torch.randn(2, 3, 4, 2, 3)
    assert torch.equal(
        wm(states, actions), states
    )  # every input's layout survives the first steps of training
    nxt, _ = wm.step(states[:, 0], actions[:, 0], None)
    assert torch.equal(nxt, states[:, 0])
    target = states + 1.0
    opt = torch.optim.Adam(wm.parameters(), lr=1e-2)
    for _ in range(50):
        opt.zero_grad()
        loss = (wm(states, actions) - target).abs().mean()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5
    cache = None
    full = wm.eval()(states, actions)
    for i in range(3):  # the cached path adds the same residual
        nxt, cache = wm.step(states[:, i], actions[:, i], cache)
        assert torch.allclose(nxt, full[:, i], atol=1e-5)
