"""PairDataset: pairing, sample contract, splits, determinism, frame cache and its invalidation."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from data_fixtures import make_recording

from studio.data.episode import Episode
from studio.data.splits import SplitSpec
from studio.data.store import EpisodeStore
from studio.data.training_view import PairDataset, even_indices, stratified_indices

T1, T2, T3 = "pick_place/cube->red", "pick_place/cube->green", "pick_place/bar->blue"
SPEC = SplitSpec(scene="pick_place", train=(T1, T2), test=(T3,), val_fraction=0.25)
SIZE = (24, 32)


@pytest.fixture
def store(tmp_path):
    s = EpisodeStore(tmp_path)
    seed = 0
    for task in (T1, T2, T3):
        for _ in range(4):
            s.add_episode(
                make_recording(task=task, robot="sawyer", seed=seed), role="expert", source="scripted"
            )
            seed += 1
        for _ in range(4):
            rec = make_recording(
                task=task, robot="panda", seed=seed, steps=40 + seed, num_frames=20 + seed % 3
            )
            s.add_episode(rec, role="agent", source="scripted")
            seed += 1
    # Excluded: a failed teleop agent episode and a rollout.
    s.add_episode(make_recording(task=T1, seed=100, success=False), role="agent", source="teleop")
    s.add_episode(make_recording(task=T1, seed=101), role="agent", source="rollout")
    # Included as an expert: a human video (no per-step arrays).
    ep = Episode.from_recording(make_recording(task=T2, seed=102), role="expert", source="upload")
    human = Episode(
        ep.meta.__class__(
            **{
                **ep.meta.to_dict(),
                "embodiment": "human",
                "num_steps": 0,
                "seed": None,
                "success": None,
                "control_dt": None,
            }
        ),
        ep.camera,
        ep.frames,
        ep.frame_times,
    )
    s.add_episode(human)
    return s


def _dataset(store, split="train", **kw):
    return PairDataset(store, split=split, image_size=SIZE, split_spec=SPEC, **kw)


def test_pairs_same_task_expert_and_agent(store):
    ds = _dataset(store)
    assert ds.tasks == [T1, T2]
    e, a = ds.pairs[:, 0], ds.pairs[:, 1]
    for ei, ai, ti in zip(e, a, ds.pair_tasks):
        me, ma = ds.episodes[ei], ds.episodes[ai]
        assert me.task == ma.task == ds.tasks[ti]
        assert me.role == "expert" and ma.role == "agent"
        assert ma.source == "scripted" and ma.success
    # 4 experts (T1) / 5 (T2, with the human) and 4 agents per task; one of each held out for validation.
    assert len(ds) == 3 * 3 + 4 * 3
    val = _dataset(store, "val")
    humans = [m for d in (ds, val) for m in d.episodes if m.embodiment == "human"]
    assert len(humans) == 1 and humans[0].task == T2
    # Every expert is paired with every agent of its task.
    for ei in set(e.tolist()):
        agents = a[ds.agents_of_expert(ei)]
        task = ds.episodes[ei].task
        assert sorted(agents) == sorted({int(x) for x, t in zip(a, ds.pair_tasks) if ds.tasks[t] == task})


def test_hand_demonstrations_pair_with_panda_agents_alone(store):
    # The simulated hand's demonstrations (embodiment "human", with robot state) and a Panda demonstration.
    for i, task in enumerate((T1, T1, T1, T2, T2, T2)):
        store.add_episode(
            make_recording(task=task, robot="hand", seed=200 + i), role="expert", source="scripted"
        )
    store.add_episode(make_recording(task=T1, robot="panda", seed=300), role="expert", source="scripted")
    # Which episodes are held out for validation depends on their (random) ids: look at both splits.
    both = [_dataset(store, split) for split in ("train", "val")]
    assert {m.embodiment for d in both for m in d.episodes if m.role == "expert"} == {
        "sawyer",
        "human",
        "panda",
    }
    experts = set()
    for split in ("train", "val"):
        ds = _dataset(store, split, expert_embodiments=["human"])
        for ei, ai in ds.pairs:
            me, ma = ds.episodes[ei], ds.episodes[ai]
            assert (me.role, me.embodiment) == ("expert", "human") and (ma.role, ma.embodiment) == (
                "agent",
                "panda",
            )
            assert me.task == ma.task
            experts.add(me.id)
    assert len(experts) == 7  # the six hand demonstrations and T2's uploaded video
    panda = [_dataset(store, split, expert_embodiments=["panda"]) for split in ("train", "val")]
    assert sum(len(d) for d in panda) > 0
    assert {d.episodes[e].embodiment for d in panda for e in d.pairs[:, 0]} == {"panda"}


def test_sample_contract(store):
    ds = _dataset(store)
    H, W = SIZE
    for i in (0, len(ds) - 1):
        s = ds[i]
        assert set(s) == {
            "expert_frames",
            "agent_frames",
            "path",
            "K",
            "T_world_cam",
            "task_index",
            "expert_index",
            "agent_index",
        }
        assert s["expert_frames"].shape == (10, 3, H, W) and s["expert_frames"].dtype == np.uint8
        assert s["agent_frames"].shape == (6, 3, H, W) and s["agent_frames"].dtype == np.uint8
        assert s["path"].shape == (50, 4) and s["path"].dtype == np.float32
        assert s["K"].shape == (3, 3) and s["K"].dtype == np.float32
        assert s["T_world_cam"].shape == (4, 4) and s["T_world_cam"].dtype == np.float32
        for k in ("task_index", "expert_index", "agent_index"):
            assert s[k].dtype == np.int64
        e, a = int(s["expert_index"]), int(s["agent_index"])
        frames_e = ds.frames(e)
        np.testing.assert_array_equal(s["expert_frames"][0], frames_e[0])
        np.testing.assert_array_equal(s["expert_frames"][-1], frames_e[-1])
        frames_a = ds.frames(a)
        np.testing.assert_array_equal(s["agent_frames"], frames_a[even_indices(len(frames_a), 6)])
        # Path: camera-frame ee position and gripper command at 50 evenly spaced steps of the whole episode.
        meta = ds.episodes[a]
        _, _, arrays = store.load_arrays(meta.id)
        steps = even_indices(meta.num_steps, 50)
        assert steps[0] == 0 and steps[-1] == meta.num_steps - 1
        np.testing.assert_allclose(s["path"][:, :3], arrays["ee_pos_cam"][steps], rtol=1e-6)
        np.testing.assert_array_equal(s["path"][:, 3], arrays["gripper_cmd"][steps] > 0.5)
        # K at the sample's size projects the path onto the right pixels of the resized image.
        cam = store.load_camera(meta.id)
        np.testing.assert_allclose(s["K"], cam.resized(H, W).K, rtol=1e-6)
        uv_small = s["path"][:, :3] @ s["K"].T
        uv_full = arrays["ee_pos_cam"][steps] @ cam.K.T
        np.testing.assert_allclose(
            uv_small[:, :2] / uv_small[:, 2:], uv_full[:, :2] / uv_full[:, 2:] * [W / 64, H / 48], rtol=1e-4
        )


def _store_with_half_idle_grippers(root) -> EpisodeStore:
    """A store of three tasks whose agent episodes command 0.5 (effort 0) for their first half, then 0.8."""
    s = EpisodeStore(root)
    for seed, task in enumerate((T1, T2, T3)):
        s.add_episode(make_recording(task=task, robot="sawyer", seed=seed), role="expert", source="scripted")
        rec = make_recording(task=task, robot="panda", seed=10 + seed)
        steps = len(rec.arrays["gripper_cmd"])
        rec.arrays["gripper_cmd"] = np.where(np.arange(steps) < steps // 2, 0.5, 0.8)
        s.add_episode(rec, role="agent", source="scripted")
    return s


def test_gripper_labels_are_binary_and_an_effort_of_zero_is_open(tmp_path):
    """Meta-World's experts that do not grasp record exactly 0.5 (effort 0): the training label is open (0), and a
    grasp's 0.8 is closed (1), as the paper's binary gripper state."""
    s = _store_with_half_idle_grippers(tmp_path)
    ds = PairDataset(
        s,
        split="train",
        image_size=SIZE,
        split_spec=SplitSpec(scene="pick_place", train=(T1, T2), test=(T3,)),
    )
    for i in range(len(ds)):
        labels = ds[i]["path"][:, 3]
        assert set(np.unique(labels)) == {0.0, 1.0}
        half = len(labels) // 2
        assert (labels[: half - 1] == 0).all() and (labels[half + 1 :] == 1).all()


def test_recorded_gripper_labels_keep_the_command_and_unknown_labels_are_refused(tmp_path):
    """``gripper_labels="recorded"`` gives the recorded command itself (0.5 stays 0.5): what the shipped Meta-World
    policy was trained on; a label rule that does not exist fails with the choices."""
    s = _store_with_half_idle_grippers(tmp_path)
    spec = SplitSpec(scene="pick_place", train=(T1, T2), test=(T3,))
    ds = PairDataset(s, split="train", image_size=SIZE, split_spec=spec, gripper_labels="recorded")
    for i in range(len(ds)):
        np.testing.assert_allclose(np.unique(ds[i]["path"][:, 3]), [0.5, 0.8], rtol=1e-6)
    with pytest.raises(ValueError, match="gripper_labels must be one of"):
        PairDataset(s, split="train", image_size=SIZE, split_spec=spec, gripper_labels="soft")


def test_frames_match_store_at_training_size(store):
    ds = _dataset(store)
    e = int(ds.pairs[0, 0])
    full = store.load_frames(ds.episodes[e].id)
    cached = ds.frames(e)
    assert isinstance(cached, np.memmap)
    assert cached.shape == (len(full), 3, *SIZE)
    # Area-downscaled by 2: the cached frame equals the 2x2 block mean of the decoded frame (±1 rounding).
    block = full[0].reshape(SIZE[0], 2, SIZE[1], 2, 3).astype(float).mean(axis=(1, 3)).transpose(2, 0, 1)
    assert np.abs(cached[0] - block).max() <= 1.0


def test_splits_disjoint(store):
    train, val, test = (_dataset(store, split) for split in ("train", "val", "test"))
    ids = [{m.id for m in d.episodes} for d in (train, val, test)]
    assert not ids[0] & ids[1] and not ids[0] & ids[2] and not ids[1] & ids[2]
    assert val.tasks == [T1, T2] and test.tasks == [T3]
    assert len(val) == 2  # one held-out expert x one held-out agent per training task
    assert len(test) == 16
    assert {m.task for m in test.episodes} == {T3}


def test_stratified_and_even_indices():
    rng = np.random.default_rng(0)
    for length in (10, 17, 100):
        for _ in range(20):
            idx = stratified_indices(length, 10, rng)
            assert idx[0] == 0 and idx[-1] == length - 1
            edges = np.floor(np.arange(11) * length / 10).astype(int)
            assert np.all(idx[1:-1] >= edges[1:-2]) and np.all(idx[1:-1] < edges[2:-1])
    short = stratified_indices(4, 10, rng)
    assert short.shape == (10,) and short.min() == 0 and short.max() == 3
    assert even_indices(21, 6).tolist() == [0, 4, 8, 12, 16, 20]


def test_deterministic_by_seed_and_epoch(store):
    a, b = _dataset(store, seed=3), _dataset(store, seed=3)
    draws = [a[i]["expert_frames"] for i in range(len(a))]
    for i in range(len(a)):
        np.testing.assert_array_equal(draws[i], b[i]["expert_frames"])
    a.set_epoch(1)
    assert any(not np.array_equal(draws[i], a[i]["expert_frames"]) for i in range(len(a)))


def test_cache_invalidation(store):
    # No validation hold-out here: which episodes are held out depends on their (random) ids.
    spec = SplitSpec(scene="pick_place", train=(T1, T2), test=(T3,), val_fraction=0.0)
    ds = PairDataset(store, image_size=SIZE, split_spec=spec)
    fp = ds.fingerprint()
    assert PairDataset(store, image_size=SIZE, split_spec=spec).fingerprint() == fp
    assert PairDataset(store, image_size=(12, 16), split_spec=spec).fingerprint() != fp
    files = set(ds.cache_dir.glob("*.npy"))
    assert {f.stem for f in files} == {m.id for m in ds.episodes}
    # A new agent episode: new pairs, new fingerprint, its frames decoded into the cache.
    new = store.add_episode(make_recording(task=T1, seed=500), role="agent", source="teleop")
    assert ds.refresh()
    assert ds.fingerprint() != fp
    assert (ds.cache_dir / f"{new.id}.npy").is_file()
    assert any(ds.episodes[a].id == new.id for a in ds.pairs[:, 1])
    # Deleting it: back to the old fingerprint, cache file gone.
    store.delete_episode(new.id)
    assert ds.refresh() and ds.fingerprint() == fp
    assert not (ds.cache_dir / f"{new.id}.npy").exists()
    assert not ds.refresh()
    # A corrupt cache file is rebuilt, not trusted.
    victim = ds.cache_dir / f"{ds.episodes[0].id}.npy"
    victim.write_bytes(b"junk")
    again = PairDataset(store, image_size=SIZE, split_spec=spec)
    assert again.frames(0).shape[1:] == (3, *SIZE)


def test_pickles_for_worker_processes(store):
    ds = _dataset(store)
    ds[0]
    copy = pickle.loads(pickle.dumps(ds))
    for k, v in ds[5].items():
        np.testing.assert_array_equal(copy[5][k], v)
    with pytest.raises(RuntimeError):
        copy.refresh()


def test_torch_dataloader_batches(store):
    torch = pytest.importorskip("torch")
    torch.set_num_threads(1)
    ds = _dataset(store)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4, shuffle=True, num_workers=0)))
    assert batch["expert_frames"].shape == (4, 10, 3, *SIZE)
    assert batch["path"].dtype == torch.float32


def test_bad_arguments(store):
    with pytest.raises(ValueError, match="split"):
        _dataset(store, split="holdout")
    with pytest.raises(ValueError):
        _dataset(store, n_expert=1)
    with pytest.raises(IndexError):
        _dataset(store)[10_000]
