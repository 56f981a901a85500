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

#: A policy file's optional guided branch (``studio export-policy --guided-from``; ``studio.model.guidance``): the
#: weights of every part but the encoder, which it shares with the policy's own.
GUIDED_WEIGHTS = "guided_model"


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


def _plain(value: Any) -> Any:
    """A configuration value as JSON holds it (tuples as lists), so that a config read back compares equal."""
    return [_plain(v) for v in value] if isinstance(value, (list, tuple)) else value


def _encoder_entries(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v for k, v in state.items() if k.startswith("encoder.")}


def guided_model_from_checkpoint(ckpt: dict[str, Any], device: str | torch.device = "cpu") -> OSVIWM | None:
    """The guided branch of a loaded policy file (its own encoder's weights with the branch's other parts), or
    None when it has none."""
    branch = ckpt.get(GUIDED_WEIGHTS)
    if branch is None:
        return None
    model = OSVIWM(RunConfig.from_dict(ckpt["config"]).model)
    model.load_state_dict({**_encoder_entries(ckpt["model"]), **branch})
    return model.to(device)


def check_guided_branch(model: OSVIWM, branch: OSVIWM) -> None:
    """Refuse (``ValueError``) a guided branch that cannot plan beside ``model``: another architecture, another
    encoder, or a model that never guides (no guidance, or no gate: every demonstration would take the branch)."""
    from studio.model.config import PLANNING_FIELDS

    if model.cfg.guidance == 1.0 or model.cfg.guidance_gate <= 0.0:
        raise ValueError(
            "a guided branch needs guidance and a gate: it plans the demonstrations whose gain reaches the gate"
        )
    differ = [
        name
        for name, value in vars(model.cfg).items()
        if name not in PLANNING_FIELDS and _plain(getattr(branch.cfg, name)) != _plain(value)
    ]
    if differ:
        raise ValueError(f"the guided branch's network differs in model.{', model.'.join(differ)}")
    mine, theirs = _encoder_entries(model.state_dict()), _encoder_entries(branch.state_dict())
    if mine.keys() != theirs.keys() or any(
        not torch.equal(v.float(), theirs[k].float()) for k, v in mine.items()
    ):
        raise ValueError(
            "the guided branch's encoder weights differ: the two share one encoder (train both from a common "
            "start with train.freeze=encoder)"
        )
