"""Reading an OSVI-WM training checkpoint back: its format tag, the checked dictionary and the network it holds.

``studio train`` writes checkpoints (:mod:`studio.model.train`); planning, evaluation, the decoder's training and
``studio export-policy`` read them through :func:`load_checkpoint` and :func:`model_from_checkpoint`, so that
inference never imports the trainer. Files are read weights-only (:func:`studio.model.run_files.read_torch_file`):
a checkpoint a user names cannot run code. What a checkpoint says about itself without torch is
:mod:`studio.model.checkpoint_info`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from studio.model.config import RunConfig
from studio.model.osvi_wm import OSVIWM
from studio.model.run_files import read_torch_file

#: The ``format`` entry of every checkpoint ``studio train`` writes (and of the policy files exported from them).
CHECKPOINT_FORMAT = "osvi-wm-checkpoint/1"


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by ``train`` and check its format."""
    ckpt = read_torch_file(path, map_location)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not an OSVI-WM checkpoint (format {CHECKPOINT_FORMAT})")
    return ckpt


def model_from_checkpoint(ckpt: dict[str, Any], device: str | torch.device = "cpu") -> OSVIWM:
    """The network of a loaded checkpoint, built from its configuration with its weights, on ``device``."""
    run = RunConfig.from_dict(ckpt["config"])
    model = OSVIWM(run.model)
    model.load_state_dict(ckpt["model"])
    return model.to(device)
