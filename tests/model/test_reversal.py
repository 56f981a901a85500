"""Time-reversed training pairs: a demonstration and exactly its pairs flip together; the loss sees the flip."""

from __future__ import annotations

import pytest
import torch
from synthetic_pairs import SyntheticPairs, tiny_run_config

from studio.model.batching import collate_pairs
from studio.model.config import TrainConfig
from studio.model.osvi_wm import OSVIWM
from studio.model.reversal import reverse_pairs
from studio.model.train import compute_losses

torch.set_num_threads(1)


def _batch():
    run = tiny_run_config()
    data = SyntheticPairs(n_tasks=3, episodes_per_task=2)
    # two pairs per demonstration: (0, 1) share one, (4, 5) another, (8, 9) a third (SyntheticPairs' layout)
    batch = collate_pairs([data[i] for i in (0, 1, 4, 5, 8, 9)], run.model.image_size)
    return run, batch


def test_a_reversed_demonstration_and_all_its_pairs_are_played_backwards_and_the_rest_is_untouched():
    _, batch = _batch()
    assert batch.expert_frames.shape[0] >= 2  # the batch holds several demonstrations
    seen_mixed = False
    for seed in range(20):
        out, chosen = reverse_pairs(batch, 0.5, torch.Generator().manual_seed(seed))
        seen_mixed |= bool(chosen.any()) and not bool(chosen.all())
        for u in range(batch.expert_frames.shape[0]):
            want = batch.expert_frames[u].flip(0) if chosen[u] else batch.expert_frames[u]
            assert torch.equal(out.expert_frames[u], want)
        for b in range(batch.size):
            flipped = bool(chosen[batch.expert_ids[b]])
            for name, dim in (("agent_frames", 0), ("path", 0)):
                original = getattr(batch, name)[b]
                assert torch.equal(getattr(out, name)[b], original.flip(dim) if flipped else original)
            assert torch.equal(out.K[b], batch.K[b]) and torch.equal(out.T_world_cam[b], batch.T_world_cam[b])
        assert torch.equal(out.expert_ids, batch.expert_ids)
    assert seen_mixed  # some draws reverse part of the batch: the per-demonstration choice is exercised


def test_probability_zero_keeps_the_batch_and_one_reverses_it_all_and_twice_is_the_original():
    _, batch = _batch()
    same, chosen = reverse_pairs(batch, 0.0, torch.Generator().manual_seed(0))
    assert same is batch and not chosen.any()
    once, chosen = reverse_pairs(batch, 1.0, torch.Generator().manual_seed(0))
    assert chosen.all()
    assert not torch.equal(once.path, batch.path)
    twice, _ = reverse_pairs(once, 1.0, torch.Generator().manual_seed(0))
    for name in ("expert_frames", "agent_frames", "path"):
        assert torch.equal(getattr(twice, name), getattr(batch, name))
    assert batch.path.data_ptr() != once.path.data_ptr()  # the input batch is not modified in place


def test_training_with_reverse_sees_exactly_the_reversed_pairs():
    run, batch = _batch()
    torch.manual_seed(0)
    core = OSVIWM(run.model).eval()
    reversed_run = run.with_overrides(["train.reverse=1.0"])

    with_flag = compute_losses(core, core, batch, reversed_run, 0, 10, torch.Generator().manual_seed(3))[1]
    g = torch.Generator().manual_seed(3)
    flipped, _ = reverse_pairs(batch, 1.0, g)  # consumes the same draws the flag does
    by_hand = compute_losses(core, core, flipped, run, 0, 10, g)[1]
    forward = compute_losses(core, core, batch, run, 0, 10, torch.Generator().manual_seed(3))[1]
    assert with_flag["loss_sdtw"] == pytest.approx(by_hand["loss_sdtw"], abs=1e-6)
    assert abs(with_flag["loss_sdtw"] - forward["loss_sdtw"]) > 1e-4
    # validation (no generator) never reverses
    assert (
        compute_losses(core, core, batch, reversed_run, 0, 10, None)[1]
        == compute_losses(core, core, batch, run, 0, 10, None)[1]
    )


@pytest.mark.parametrize("value", [-0.1, 1.5])
def test_reverse_must_be_a_probability(value):
    with pytest.raises(ValueError, match="reverse must be a probability"):
        TrainConfig(reverse=value)
