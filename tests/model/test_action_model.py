"""The action model π: causality over frames, step-by-step equals one pass, map and vector states."""

from __future__ import annotations

import pytest
import torch

from studio.model.action_model import ActionModel

torch.set_num_threads(1)


@pytest.mark.parametrize("attention", ["joint", "divided", "cross"])
@pytest.mark.parametrize("state_shape", [(8, 3, 4), (12,)])
def test_stepping_on_the_expert_cache_equals_one_causal_pass(state_shape, attention):
    torch.manual_seed(0)
    pi = ActionModel(state_shape, blocks=2, heads=2, attn_dim=8, mlp_dim=16, attention=attention).eval()
    expert = torch.randn(2, 4, *state_shape)
    agent = torch.randn(2, 3, *state_shape)
    full = pi(torch.cat([expert, agent], 1), expert_frames=4)
    cache = pi.context(expert)
    for i in range(3):
        action, cache = pi.step(agent[:, i], cache)
        assert action.shape == (2, *state_shape)
        assert torch.allclose(action, full[:, 4 + i], atol=1e-5)


@pytest.mark.parametrize("attention", ["joint", "divided", "cross"])
def test_changing_a_later_frame_never_changes_an_earlier_latent_action(attention):
    torch.manual_seed(0)
    pi = ActionModel((8, 3, 4), blocks=2, heads=2, attn_dim=8, mlp_dim=16, attention=attention).eval()
    seq = torch.randn(1, 7, 8, 3, 4)  # 4 expert frames then 3 agent frames
    out = pi(seq, expert_frames=4)
    for t in range(1, 7):
        changed = seq.clone()
        changed[:, t] = torch.randn(1, 8, 3, 4)
        out2 = pi(changed, expert_frames=4)
        assert torch.allclose(out[:, :t], out2[:, :t], atol=1e-6), f"output before frame {t} changed"
        assert not torch.allclose(out[:, t], out2[:, t])


def test_cells_are_told_apart_by_the_grid_code():
    torch.manual_seed(0)
    pi = ActionModel((8, 2, 2), blocks=1, heads=2, attn_dim=8, mlp_dim=0).eval()
    seq = torch.zeros(1, 2, 8, 2, 2)  # identical content in every cell
    out = pi(seq, expert_frames=1)
    assert not torch.allclose(out[0, 0, :, 0, 0], out[0, 0, :, 1, 1])
