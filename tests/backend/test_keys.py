"""Key expressions: builders and parsers agree, and names that would break a key are refused."""

from __future__ import annotations

import pytest
import zenoh

from studio.backend import keys


def test_builders_and_parsers_round_trip():
    assert keys.worker_token("sim", "sim-a") == "studio/workers/sim/sim-a"
    assert keys.parse_worker_key(keys.worker_key("train", "t.1", "status")) == ("train", "t.1", "status")
    assert keys.parse_worker_key(keys.worker_token("sim", "w")) == ("sim", "w", None)
    assert keys.parse_session_key(keys.session_key("w", "s-1", "poses")) == ("w", "s-1", "poses")
    assert keys.parse_job_key(keys.job_key("job_1", "progress")) == ("job_1", "progress")
    assert keys.parse_upload_key(keys.upload_key("t-9")) == "t-9"


def test_selectors_match_exactly_their_keys():
    def ke(k):
        return zenoh.KeyExpr(k)

    assert ke(keys.ALL_WORKER_TOKENS).intersects(ke(keys.worker_token("sim", "a")))
    assert not ke(keys.ALL_WORKER_TOKENS).intersects(ke(keys.worker_key("sim", "a", "status")))
    assert ke(keys.ALL_WORKER_STATUS).intersects(ke(keys.worker_key("train", "b", "status")))
    assert ke(keys.all_jobs("status")).intersects(ke(keys.job_key("j", "status")))
    assert not ke(keys.all_jobs("status")).intersects(ke(keys.job_key("j", "result")))
    assert ke(keys.all_sessions("w", "ctl")).intersects(ke(keys.session_key("w", "s", "ctl")))
    assert not ke(keys.all_sessions("w", "ctl")).intersects(ke(keys.session_key("v", "s", "ctl")))


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a*", "$x", "a?b", "a#b", "-lead", "x" * 65, "é"])
def test_unusable_names_are_refused(bad):
    with pytest.raises(keys.KeyExprError, match="not usable in a key"):
        keys.job_key(bad, "status")


@pytest.mark.parametrize(
    "key", ["studio/jobs/a", "studio/jobs/a/nope", "other/jobs/a/status", "studio/jobs/*/status"]
)
def test_parsers_refuse_other_keys(key):
    with pytest.raises(keys.KeyExprError):
        keys.parse_job_key(key)


def test_unknown_leaf_is_refused():
    with pytest.raises(keys.KeyExprError, match="unknown key leaf"):
        keys.session_key("w", "s", "nope")
