"""Scripted collection: seeds per slot, resume, failure accounting, parallel workers, the real experts."""

from __future__ import annotations

import pytest

from studio.data.collect import CollectConfig, collect, episode_seed
from studio.data.splits import resolve_tasks
from studio.data.store import EpisodeStore

TASK = "pick_place/cube->red"


def test_episode_seed_is_stable_and_distinct():
    assert episode_seed(0, "panda", TASK, 3) == episode_seed(0, "panda", TASK, 3)
    seeds = {
        episode_seed(s, r, TASK, i, a)
        for s in (0, 1)
        for r in ("panda", "sawyer")
        for i in range(5)
        for a in (0, 1)
    }
    assert len(seeds) == 40
    assert 0 <= episode_seed(123, "sawyer", TASK, 99, 4) < 2**31


def test_resolve_tasks():
    assert len(resolve_tasks("pick_place", ["all"])) == 16
    assert resolve_tasks("pick_place", ["test"]) == ["pick_place/bar->blue", "pick_place/bar->yellow"]
    assert len(resolve_tasks("pick_place", ["train", TASK])) == 14
    with pytest.raises(ValueError, match="unknown task"):
        resolve_tasks("pick_place", ["pick_place/cube->purple"])


def test_config_validation():
    with pytest.raises(ValueError, match="robot"):
        CollectConfig(robot="ur5")
    with pytest.raises(ValueError, match="only demonstrates"):
        CollectConfig(robot="hand", role="agent")
    with pytest.raises(ValueError, match="role"):
        CollectConfig(robot="panda", role="teacher")
    with pytest.raises(ValueError, match="20 frames"):
        CollectConfig(min_frames=10)


def _flaky(tmp_path, **kw):
    base = dict(
        robot="panda",
        tasks=[TASK],
        episodes=6,
        seed=0,
        image_size=(48, 64),
        data_dir=str(tmp_path),
        recorder="data_fixtures:flaky_recorder",
        progress=False,
    )
    return CollectConfig(**{**base, **kw})


def test_failures_discarded_and_counted(tmp_path):
    result = collect(_flaky(tmp_path))
    expected_failures = 0
    for i in range(6):
        a = 0
        while episode_seed(0, "panda", TASK, i, a) % 3 == 0:
            a += 1
        expected_failures += a
    assert (result.made, result.failed_attempts, result.missing) == (6, expected_failures, [])
    store = EpisodeStore(tmp_path)
    metas = store.episodes()
    assert all(m.success and m.role == "agent" and m.source == "scripted" for m in metas)
    # The stored seed is the first successful attempt's seed of the slot.
    for m in metas:
        assert m.seed == episode_seed(0, "panda", TASK, m.collect_index, m.extra["attempt"])


def test_slots_failing_every_attempt_stay_missing(tmp_path):
    result = collect(_flaky(tmp_path, max_attempts=1))
    failing = [i for i in range(6) if episode_seed(0, "panda", TASK, i) % 3 == 0]
    assert result.missing == [(TASK, i) for i in failing]
    assert result.made == 6 - len(failing)


def test_real_experts_resume_and_determinism(tmp_path):
    """Real scripted Sawyer episodes (tiny images): resume makes only missing slots, with the same seeds."""
    cfg = CollectConfig(
        robot="sawyer", tasks=[TASK], episodes=2, image_size=(48, 64), data_dir=str(tmp_path), progress=False
    )
    first = collect(cfg)
    assert (first.made, first.already_present) == (2, 0)
    store = EpisodeStore(tmp_path)
    metas = store.episodes()
    assert {m.collect_index for m in metas} == {0, 1}
    assert all(m.num_frames >= 20 and m.role == "expert" and m.embodiment == "sawyer" for m in metas)
    assert all((m.height, m.width) == (48, 64) for m in metas)
    # Interrupted run: one slot lost; a bigger run resumes with the missing ones only.
    lost = store.delete_last()
    cfg.episodes = 3
    second = collect(cfg)
    assert (second.made, second.already_present) == (2, 1)
    again = {m.collect_index: m for m in store.episodes()}
    assert sorted(again) == [0, 1, 2]
    assert again[lost.collect_index].seed == lost.seed  # deterministic by seed
    assert collect(cfg).made == 0


def test_two_workers(tmp_path):
    cfg = _flaky(tmp_path, workers=2, episodes=4)
    result = collect(cfg)
    assert result.made == 4 and not result.errors
    assert sorted(m.collect_index for m in EpisodeStore(tmp_path).episodes()) == [0, 1, 2, 3]


def test_cli(tmp_path, capsys):
    from studio.cli import main

    argv = [
        "collect",
        "--robot",
        "panda",
        "--tasks",
        TASK,
        "--episodes",
        "1",
        "--image-size",
        "48",
        "64",
        "--data-dir",
        str(tmp_path),
        "--no-progress",
    ]
    assert main(argv) == 0
    assert "collected 1 episodes" in capsys.readouterr().out
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "collected 0 episodes" in out and "1 were already present" in out
    (meta,) = EpisodeStore(tmp_path).episodes()
    assert (meta.embodiment, meta.role) == ("panda", "agent")
    assert main([*argv[:4], "pick_place/cube->purple", *argv[5:]]) == 2
    assert "unknown task" in capsys.readouterr().err


def test_roles_and_embodiments_of_a_run():
    assert (CollectConfig(robot="sawyer").episode_role, CollectConfig(robot="sawyer").embodiment) == (
        "expert",
        "sawyer",
    )
    hand = CollectConfig(robot="hand")
    assert (hand.episode_role, hand.embodiment, hand.seed_key) == ("expert", "human", "hand")
    agent, expert = CollectConfig(robot="panda"), CollectConfig(robot="panda", role="expert")
    assert (agent.episode_role, agent.seed_key) == ("agent", "panda")  # the seeds of existing runs are kept
    assert (expert.episode_role, expert.seed_key) == ("expert", "panda:expert")


def test_hand_collects_human_demonstrations(tmp_path):
    cfg = CollectConfig(
        robot="hand", tasks=[TASK], episodes=2, image_size=(48, 64), data_dir=str(tmp_path), progress=False
    )
    assert collect(cfg).made == 2
    store = EpisodeStore(tmp_path)
    metas = store.episodes()
    assert all((m.role, m.embodiment, m.source) == ("expert", "human", "scripted") for m in metas)
    assert all(m.success and m.seed is not None and m.has_arrays for m in metas)
    _, _, arrays = store.load_arrays(metas[0].id)
    assert arrays["qpos"].shape[1] == 18  # three slide joints, fifteen finger joints
    assert arrays["gripper_cmd"].max() == 1.0
    assert collect(cfg).made == 0  # resumes: its slots are the hand's


def test_panda_as_expert_beside_panda_as_agent(tmp_path, capsys):
    from studio.cli import main

    argv = [
        "collect",
        "--robot",
        "panda",
        "--tasks",
        TASK,
        "--episodes",
        "1",
        "--image-size",
        "48",
        "64",
        "--data-dir",
        str(tmp_path),
        "--no-progress",
    ]
    assert main([*argv, "--role", "expert"]) == 0
    assert main(argv) == 0
    assert main([*argv, "--role", "expert"]) == 0  # already there
    assert "collected 0 episodes" in capsys.readouterr().out.splitlines()[-1]
    metas = {m.role: m for m in EpisodeStore(tmp_path).episodes()}
    assert set(metas) == {"expert", "agent"}
    assert metas["expert"].embodiment == metas["agent"].embodiment == "panda"
    assert metas["expert"].collect_index == metas["agent"].collect_index == 0
    assert metas["expert"].seed != metas["agent"].seed
    assert main(["collect", "--robot", "hand", "--role", "agent", "--data-dir", str(tmp_path)]) == 2
