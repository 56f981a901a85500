"""A checkpoint's metadata (its tasks, hence its scene) read without torch, as the browser studio reads it."""

from __future__ import annotations

import collections
import pickle
import zipfile

import pytest
import torch

from studio.data.paths import SHIPPED_POLICY_DIR
from studio.model.checkpoint_info import TENSOR, checkpoint_scene, read_checkpoint_info, scene_of_tasks


def test_reads_what_torch_load_reads_except_the_tensors(tmp_path):
    state = collections.OrderedDict(w=torch.ones(3, 2), b=torch.zeros(2, dtype=torch.float16))
    ckpt = {
        "format": "osvi-wm-checkpoint/1",
        "tasks": ["push/red-forward", "push/blue-forward"],
        "step": 7,
        "config": {"model": {"image_size": [72, 96]}},
        "model": state,
        "torch_version": torch.__version__,
        "best_val_loss": 0.25,
    }
    path = tmp_path / "ck.pt"
    torch.save(ckpt, path)
    info = read_checkpoint_info(path)
    assert {k: v for k, v in info.items() if k != "model"} == {
        **{k: v for k, v in ckpt.items() if k != "model"},
        "torch_version": str(torch.__version__),
    }
    assert list(info["model"]) == ["w", "b"] and all(isinstance(v, TENSOR) for v in info["model"].values())
    assert checkpoint_scene(path) == "push"


@pytest.mark.parametrize(
    "policy",
    sorted(p for p in SHIPPED_POLICY_DIR.glob("*.pt") if not p.name.endswith(".decoder.pt")),
    ids=lambda p: p.stem,
)
def test_the_shipped_policies_name_their_scene(policy):
    tasks = torch.load(policy, map_location="cpu", weights_only=False)["tasks"]
    assert read_checkpoint_info(policy)["tasks"] == tasks
    assert checkpoint_scene(policy) == tasks[0].split("/")[0] and policy.stem.startswith(
        checkpoint_scene(policy).replace("_", "-")
    ), "a shipped policy's name starts with its scene"


def test_unreadable_or_sceneless_files_have_no_scene(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a zip")
    assert checkpoint_scene(tmp_path / "junk.pt") is None
    assert checkpoint_scene(tmp_path / "missing.pt") is None
    with pytest.raises(ValueError, match="not a torch checkpoint"):
        read_checkpoint_info(tmp_path / "junk.pt")
    torch.save({"tasks": []}, tmp_path / "none.pt")
    assert checkpoint_scene(tmp_path / "none.pt") is None
    assert scene_of_tasks(["pick_place/cube->red", "push/red-forward"]) is None, "tasks of two scenes"
    assert scene_of_tasks(["metaworld/door-unlock-v3"]) == "metaworld"


def test_imports_and_calls_nothing_the_file_names(tmp_path):
    class Boom:
        def __reduce__(self):
            return (print, ("this must never run",))

    with zipfile.ZipFile(tmp_path / "evil.pt", "w") as zf:
        zf.writestr("evil/data.pkl", pickle.dumps({"tasks": ["push/red-forward"], "x": Boom()}, protocol=2))
    info = read_checkpoint_info(tmp_path / "evil.pt")
    assert isinstance(info["x"], TENSOR) and checkpoint_scene(tmp_path / "evil.pt") == "push"
