"""``studio collect --scene metaworld``: Meta-World's scripted policies into the store, one pool for both roles."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from studio.data.collect import CollectConfig, collect
from studio.data.splits import resolve_tasks
from studio.data.store import EpisodeStore
from studio.data.training_view import PairDataset

TASK = "metaworld/button-press-v3"


def test_config_defaults_follow_the_scene():
    cfg = CollectConfig(scene="metaworld", robot="sawyer")
    assert cfg.recorder == "studio.sim.metaworld_experts:record_expert" and cfg.image_size == (224, 224)
    tabletop = CollectConfig(scene="push", robot="panda")
    assert tabletop.recorder == "studio.sim.experts:record_expert" and tabletop.image_size == (240, 320)
    with pytest.raises(ValueError, match="only the Sawyer"):
        CollectConfig(scene="metaworld", robot="panda")


def test_resolve_metaworld_tasks():
    assert len(resolve_tasks("metaworld", ["all"])) == 50
    assert len(resolve_tasks("metaworld", ["train"])) == 46
    assert resolve_tasks("metaworld", ["test"])[0] == TASK
    with pytest.raises(ValueError, match="unknown task"):
        resolve_tasks("metaworld", ["metaworld/juggle-v3"])


def test_collect_into_the_store_and_pair_the_pool_with_itself(tmp_path):
    cfg = CollectConfig(
        scene="metaworld",
        robot="sawyer",
        tasks=[TASK],
        episodes=2,
        image_size=(48, 48),
        data_dir=str(tmp_path),
        progress=False,
    )
    result = collect(cfg)
    assert result.made == 2 and not result.missing and not result.errors
    with EpisodeStore(tmp_path) as store:
        metas = store.episodes(task=TASK)
        assert len(metas) == 2
        assert {(m.role, m.embodiment, m.scene, m.source, m.success) for m in metas} == {
            ("expert", "sawyer", "metaworld", "scripted", True)
        }
        assert len({m.seed for m in metas}) == 2
    assert collect(cfg).already_present == 2  # resumable like the tabletop collection
    view = PairDataset(
        tmp_path, split="test", image_size=(48, 48), scene="metaworld"
    )  # the scene's own roles
    assert len(view) == 4  # 2 demonstrations x 2 trajectories of the same pool, self-pairs included
    sample = view[0]
    assert sample["expert_frames"].shape == (10, 3, 48, 48) and sample["path"].shape == (50, 4)
    assert np.all(sample["path"][:, 2] > 0.5)  # in front of the camera (camera-frame z, metres)
