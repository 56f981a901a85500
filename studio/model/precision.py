"""Which floating-point precision a training run uses on this machine: ``auto`` picks bfloat16 autocast where the
hardware computes it natively, float32 elsewhere.

bfloat16 pays only where the CPU has native instructions for it (AVX-512 BF16 or AMX, which oneDNN reports):
there a quickstart training step takes 0.66 of the float32 step's time, held-out success staying above 95 %
(docs/experiments.md, "How long from nothing to a policy?"). Where it is emulated, autocast costs time instead of
saving it, so ``auto`` falls back to float32. CUDA devices use bfloat16 where ``torch.cuda.is_bf16_supported()``
says so.
"""

from __future__ import annotations

from typing import Literal

import torch

PRECISION_CHOICES: tuple[str, ...] = ("auto", "fp32", "bf16")


def bf16_is_native(device: str | torch.device = "cpu") -> bool:
    """Whether ``device`` computes bfloat16 matrix products and convolutions natively."""
    kind = torch.device(device).type
    if kind == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if kind != "cpu":
        return False
    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


def resolve_precision(choice: str, device: str | torch.device = "cpu") -> Literal["fp32", "bf16"]:
    """``fp32`` or ``bf16`` for a choice of :data:`PRECISION_CHOICES` (``auto``: bf16 where native)."""
    if choice == "auto":
        return "bf16" if bf16_is_native(device) else "fp32"
    if choice in ("fp32", "bf16"):
        return choice  # type: ignore[return-value]  # narrowed by the test above
    raise ValueError(f"precision must be one of {', '.join(PRECISION_CHOICES)}, got {choice!r}")
