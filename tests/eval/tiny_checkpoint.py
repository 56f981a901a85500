"""A tiny untrained OSVI-WM checkpoint in the training format, for tests where planning quality is not the point.

python tests/eval/tiny_checkpoint.py OUT.pt   # the same from the command line (for tests that keep torch out)
"""

from __future__ import annotations

import sys
from pathlib import Path


def write_tiny_checkpoint(
    path: str | Path, seed: int = 0, guidance: float = 1.0, planning: tuple[str, ...] = ()
) -> Path:
    """Write an untrained small model (seeded weights) to ``path``, creating its directory; returns the path.
    ``guidance`` ≠ 1 writes a policy that plans with demonstration guidance; ``planning`` adds ``model.FIELD=VALUE``
    planning settings (its gates)."""
    import torch

    from studio.bench.synthetic_task import tiny_run_config
    from studio.model.checkpoint import CHECKPOINT_FORMAT
    from studio.model.osvi_wm import OSVIWM

    path = Path(path)
    torch.manual_seed(seed)
    run = tiny_run_config()  # the model the synthetic benchmark trains, untrained here
    if guidance != 1.0:
        run = run.with_overrides([f"model.guidance={guidance}", "train.demo_dropout=0.2", *planning])
    model = run.model
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
