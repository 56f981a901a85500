"""Recording drafts: chunks journaled in order, gaps refused, repeats trimmed, a fork's prefix read back."""

import numpy as np
import pytest

from studio.data.drafts import DraftError, RecordingDrafts

HEADER = {
    "scene": "push",
    "robot": "sawyer",
    "task": "push/red-forward",
    "seed": 1,
    "control_dt": 0.01,
    "role": "expert",
}


def chunk(first: int, n: int, width: int = 4):
    t = np.arange(first, first + n, dtype=np.float64)
    return np.repeat(t[:, None], width, axis=1), {"time": t * 0.01, "gripper_cmd": np.zeros(n)}


def test_chunks_append_in_order_and_load_back(tmp_path):
    drafts = RecordingDrafts(tmp_path)
    drafts.create("d-1", HEADER)
    assert drafts.next_step("d-1") == 0
    assert drafts.append("d-1", 0, *chunk(0, 5)) == 5
    assert drafts.append("d-1", 5, *chunk(5, 3)) == 3
    assert drafts.append("d-1", 3, *chunk(3, 7)) == 2  # ticks 3 … 7 were kept already: only 8 and 9 are new
    assert drafts.append("d-1", 0, *chunk(0, 4)) == 0
    d = drafts.load("d-1")
    np.testing.assert_array_equal(d.states[:, 0], np.arange(10))
    np.testing.assert_array_equal(d.arrays["time"], np.arange(10) * 0.01)
    assert d.num_steps == 10 and d.header["task"] == "push/red-forward" and d.header["prefix"] is None
    (info,) = drafts.drafts()
    assert info.id == "d-1" and info.steps == 10
    drafts.discard("d-1")
    assert drafts.drafts() == []


def test_a_gap_and_bad_input_are_refused_with_the_reason(tmp_path):
    drafts = RecordingDrafts(tmp_path)
    drafts.create("d-2", HEADER)
    drafts.append("d-2", 0, *chunk(0, 4))
    with pytest.raises(DraftError, match="starts at tick 6, the draft ends at tick 4"):
        drafts.append("d-2", 6, *chunk(6, 2))
    assert drafts.next_step("d-2") == 4
    with pytest.raises(DraftError, match="exists already"):
        drafts.create("d-2", HEADER)
    with pytest.raises(DraftError, match="needs"):
        drafts.create("d-3", {"scene": "push"})
    with pytest.raises(DraftError, match="not a draft id"):
        drafts.header("../etc")
    with pytest.raises(DraftError, match="no draft"):
        drafts.load("d-missing")
    states, arrays = chunk(4, 3)
    with pytest.raises(DraftError, match="n ticks of every array"):
        drafts.append("d-2", 4, states, {"time": arrays["time"][:2]})
    drafts.create("d-empty", HEADER)
    with pytest.raises(DraftError, match="holds no ticks"):
        drafts.load("d-empty")


def test_a_fork_draft_needs_the_store_for_its_prefix(tmp_path):
    drafts = RecordingDrafts(tmp_path)
    drafts.create("d-4", {**HEADER, "prefix": {"rollout": "r-1", "steps": 12}})
    assert drafts.next_step("d-4") == 12  # its own chunks start after the rollout's ticks
    with pytest.raises(DraftError, match="needs the store"):
        drafts.load("d-4")


def test_listing_skips_a_draft_discarded_while_it_is_read(tmp_path, monkeypatch):
    """The panel lists drafts twice a second while a saved recording's draft is being cleaned up: a chunk gone
    between the directory listing and its stat is a draft that is going away, not an error."""
    drafts = RecordingDrafts(tmp_path)
    drafts.create("d-gone", HEADER)
    drafts.append("d-gone", 0, *chunk(0, 3))
    drafts.create("d-kept", HEADER)
    drafts.append("d-kept", 0, *chunk(0, 2))
    listed = RecordingDrafts._chunks

    def listed_then_discarded(self, draft_id):
        found = listed(self, draft_id)
        if draft_id == "d-gone":
            self.discard(draft_id)
        return found

    monkeypatch.setattr(RecordingDrafts, "_chunks", listed_then_discarded)
    assert [d.id for d in drafts.drafts()] == ["d-kept"]
