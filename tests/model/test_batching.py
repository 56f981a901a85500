"""Collation (one expert video per demonstration, resizing with K) and deterministic grouped batch plans."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_pairs import SyntheticPairs

from studio.model.batching import BatchPlan, PairSource, collate_pairs, expert_indices_of

torch.set_num_threads(1)


def test_synthetic_source_satisfies_the_protocol():
    assert isinstance(SyntheticPairs(), PairSource)


def test_collate_stores_each_expert_video_once():
    ds = SyntheticPairs()
    idx = [0, 1, 2, 3, 9]  # pairs 0-2 share expert 0, pair 3 has expert 1, pair 9 expert 3
    batch = collate_pairs([ds[i] for i in idx])
    assert batch.expert_frames.shape[0] == 3
    assert batch.expert_ids.tolist() == [0, 0, 0, 1, 2]
    assert batch.expert_tasks.tolist() == [0, 0, 1] and batch.agent_tasks.tolist() == [0, 0, 0, 0, 1]
    for row, i in zip(batch.expert_ids.tolist(), idx):
        assert np.array_equal(batch.expert_frames[row].numpy(), ds[i]["expert_frames"])


def test_collate_resizes_frames_and_scales_intrinsics():
    ds = SyntheticPairs(image_size=(48, 64))
    batch = collate_pairs([ds[0], ds[5]], image_size=(24, 32))
    assert batch.agent_frames.shape == (2, 3, 3, 24, 32) and batch.agent_frames.dtype == torch.uint8
    assert torch.allclose(batch.K[0, :2], torch.from_numpy(ds.K[:2]) / 2)


def test_collate_rejects_bad_samples():
    ds = SyntheticPairs()
    sample = ds[0]
    with pytest.raises(ValueError, match="expects 5 expert frames per sample, the dataset gives 4"):
        collate_pairs([sample], n_expert=4 + 1)
    broken = dict(sample)
    del broken["path"]
    with pytest.raises(KeyError, match="path"):
        collate_pairs([broken])


def test_batch_plan_is_deterministic_disjoint_and_grouped():
    experts = np.repeat(np.arange(10), 4)  # 10 experts × 4 agents
    plan = BatchPlan(40, 8, seed=3, expert_indices=experts, pairs_per_expert=2)
    assert plan.batches_per_epoch == 5
    e0 = plan.epoch(0)
    assert e0 == plan.epoch(0) and e0 != plan.epoch(1)
    flat = [i for batch in e0 for i in batch]
    assert len(flat) == len(set(flat)) == 40
    for batch in e0:  # groups of two pairs sharing an expert stay contiguous
        assert all(experts[batch[i]] == experts[batch[i + 1]] for i in range(0, 8, 2))


def test_expert_indices_come_from_the_source_when_it_can_tell():
    assert np.array_equal(expert_indices_of(SyntheticPairs()), SyntheticPairs().expert_indices)

    class WithPairs:
        def __init__(self):
            self.tasks = ["t"]
            self.pairs = np.array([[4, 0], [4, 1], [7, 2]])

        def __len__(self):
            return 3

    assert expert_indices_of(WithPairs()).tolist() == [4, 4, 7]
    with pytest.raises(ValueError, match="fewer than one batch"):
        BatchPlan(3, 4, 0)
