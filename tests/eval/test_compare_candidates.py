"""Which two checkpoints a comparison starts with: the recorded held-out figure, the ranking, the pair."""

from __future__ import annotations

import json

import pytest

from studio.data.paths import SHIPPED_POLICY_DIR
from studio.eval.compare import Candidate, default_pair, rank_candidates, recorded_held_out


@pytest.mark.parametrize(
    ("name", "figure"),
    [
        ("pick-place-cpu", 1.0),
        ("pick-place-no-world-model", 0.995),
        ("pick-place-panda-demos", 0.985),
        ("pick-place-human-demos", 0.92),
        ("push-cpu", 0.99),
        ("push-human-demos", 1.0),
        ("push-panda-demos", 0.98),
        ("metaworld-cpu", 0.862),
    ],
)
def test_the_shipped_policies_record_their_held_out_success_first_in_their_summary(name, figure):
    about = json.loads((SHIPPED_POLICY_DIR / f"{name}.json").read_text())
    assert recorded_held_out(about) == pytest.approx(figure)


def test_a_numeric_held_out_success_wins_over_the_summary_and_nonsense_is_ignored():
    assert recorded_held_out({"held_out_success": 0.5, "summary": "99 % held-out"}) == 0.5
    assert recorded_held_out({"held_out_success": 7, "summary": "12.5 % held-out"}) == 0.125
    assert recorded_held_out({"held_out_success": True, "summary": "no figure"}) is None
    assert recorded_held_out({"summary": "250 % of the baseline"}) is None
    assert recorded_held_out({}) is None and recorded_held_out({"summary": 3}) is None


def test_ranking_puts_recorded_figures_first_then_the_newest_files_then_the_oracle():
    ranked = rank_candidates(
        [
            Candidate("oracle", oracle=True),
            Candidate("run-old/best", created=100.0),
            Candidate("default/b", 0.9, 50.0),
            Candidate("run-new/best", created=300.0),
            Candidate("default/a", 0.99, 10.0),
        ]
    )
    assert [c.id for c in ranked] == ["default/a", "default/b", "run-new/best", "run-old/best", "oracle"]


def test_the_pair_is_the_active_policy_against_the_best_other_one():
    cands = [
        Candidate("default/a", 0.99),
        Candidate("default/b", 0.9),
        Candidate("run/best", created=5.0),
        Candidate("oracle", oracle=True),
    ]
    assert default_pair(cands, "default/a") == ("default/a", "default/b")
    assert default_pair(cands, "run/best") == ("run/best", "default/a")
    assert default_pair(cands, "oracle") == ("oracle", "default/a")
    assert default_pair(cands, "gone/best") == ("default/a", "default/b"), (
        "an active id not offered: the best"
    )
    assert default_pair(cands) == ("default/a", "default/b")
    assert default_pair([Candidate("default/m", 0.6), Candidate("oracle", oracle=True)], "default/m") == (
        "default/m",
        "oracle",
    )
    assert default_pair([Candidate("oracle", oracle=True)]) == ("oracle", "oracle")
    with pytest.raises(ValueError, match="no checkpoint"):
        default_pair([])
