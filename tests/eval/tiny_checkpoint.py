"""A tiny untrained OSVI-WM checkpoint in the training format, for tests where planning quality is not the point.

python tests/eval/tiny_checkpoint.py OUT.pt   # the same from the command line (for tests that keep torch out)
"""

from __future__ import annotations

import sys
from pathlib import Path


def write_tiny_checkpoint(path: str | Path, seed: int = 0) -> Path:
    """Write an untrained small model (seeded weights) to ``path``, creating its directory; returns the path."""
    import torch

    from studio.model.config import ModelConfig, RunConfig, TrainConfig
    from studio.model.osvi_wm import OSVIWM
    from studio.model.train import CHECKPOINT_FORMAT

    path = Path(path)
    torch.manual_seed(seed)
    model = ModelConfig(
        image_size=(48, 64),
        n_expert_frames=4,
        n_agent_frames=3,
        encoder_stages=2,
        state_channels=16,
        action_blocks=1,
        action_heads=2,
        action_attn_dim=16,
        action_mlp_dim=32,
        wm_blocks=1,
        wm_heads=2,
        wm_width=32,
        wm_mlp_dim=64,
        head_hidden=64,
    )
    run = RunConfig(model=model, train=TrainConfig())
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "config": run.to_dict(),
            "step": 7,
            "model": OSVIWM(model).state_dict(),
        },
        path,
    )
    return path


if __name__ == "__main__":
    write_tiny_checkpoint(sys.argv[1])
