"""count_pairs: the pairs a store gives a split's tasks, equal to PairDataset's, and why episodes are left out."""

from __future__ import annotations

import pytest
from data_fixtures import make_recording

from studio.data.splits import SplitSpec
from studio.data.store import EpisodeStore
from studio.data.training_view import PairDataset, count_pairs

RED, GREEN, BLUE, HELD = (
    "pick_place/cube->red",
    "pick_place/cube->green",
    "pick_place/cube->blue",
    "pick_place/bar->blue",
)
SPEC = SplitSpec(scene="pick_place", train=(RED, GREEN, BLUE), test=(HELD,), val_fraction=0.1)


def add(store: EpisodeStore, task: str, robot: str, seed: int, success: bool = True, source: str = "teleop"):
    role = "expert" if robot == "sawyer" else "agent"
    store.add_episode(
        make_recording(task=task, robot=robot, seed=seed, success=success), role=role, source=source
    )


@pytest.fixture
def store(tmp_path):
    with EpisodeStore(tmp_path / "data") as s:
        yield s


def test_one_sawyer_and_one_panda_episode_that_failed_are_left_out_as_failed(store):
    add(store, RED, "sawyer", 0, success=False)
    add(store, RED, "panda", 1, success=False)
    count = count_pairs(store, split_spec=SPEC)
    assert count.pairs == 0
    assert count.left_out() == ["2 failed episodes (success unticked)"]
    assert "record a successful demonstration (Sawyer or hand) and a successful agent (Panda)" in (
        count.what_to_record() or ""
    )


def test_one_successful_pair_counts_as_one_and_matches_the_trainer(store):
    add(store, RED, "sawyer", 0)
    add(store, RED, "panda", 1)
    count = count_pairs(store, split_spec=SPEC)
    assert count.pairs == 1 and count.val_pairs == 0 and count.what_to_record() is None
    assert count.summary() == "**1 training pair**: 1 demonstration × 1 agent episode of cube->red"
    assert count.left_out() == []
    assert len(PairDataset(store, "train", image_size=(24, 32), split_spec=SPEC)) == 1


def test_every_reason_is_named_and_the_count_is_the_datasets(store):
    for seed in range(3):
        add(store, RED, "sawyer", seed)
    for seed in range(3, 6):
        add(store, RED, "panda", seed, source="scripted")
    add(store, RED, "panda", 6, success=False)
    add(store, GREEN, "sawyer", 7)  # a demonstration with no agent episode of its task
    add(store, BLUE, "panda", 8)  # an agent episode with no demonstration of its task
    add(store, HELD, "sawyer", 9)
    add(store, HELD, "panda", 10)
    count = count_pairs(store, split_spec=SPEC)
    train = PairDataset(store, "train", image_size=(24, 32), split_spec=SPEC)
    val = PairDataset(store, "val", image_size=(24, 32), split_spec=SPEC)
    # three of each side of cube->red: one of each held back for validation, 2 × 2 train pairs, 1 × 1 val
    assert (count.pairs, count.val_pairs) == (len(train), len(val)) == (4, 1)
    assert count.left_out() == [
        "1 failed episode (success unticked)",
        "1 demonstration of cube->green: no agent episodes of the task to pair with",
        "1 agent episode of cube->blue: no demonstrations of the task to pair with",
        "2 episodes held back for validation",
        "2 episodes of held-out tasks (bar->blue): never trained on",
    ]
    assert count.summary() == (
        "**4 training pairs** (+ 1 pair for validation): 2 demonstrations × 2 agent episodes of cube->red"
    )


def test_what_to_record_names_the_missing_side_of_a_task(store):
    add(store, GREEN, "sawyer", 0)
    assert "record a successful agent (Panda) episode of cube->green" in (
        count_pairs(store, split_spec=SPEC).what_to_record() or ""
    )
    with EpisodeStore(store.root.parent / "other") as other:
        add(other, BLUE, "panda", 1)
        assert "record a successful demonstration (Sawyer or hand) of cube->blue" in (
            count_pairs(other, split_spec=SPEC).what_to_record() or ""
        )


def test_the_expert_embodiment_filter_is_the_datasets(store):
    add(store, RED, "sawyer", 0)
    add(store, RED, "panda", 1)
    assert count_pairs(store, split_spec=SPEC, expert_embodiments=("human",)).pairs == 0
    assert (
        len(PairDataset(store, "train", image_size=(24, 32), split_spec=SPEC, expert_embodiments=("human",)))
        == 0
    )
