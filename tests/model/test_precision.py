"""The training precision ``auto`` resolves to: bfloat16 only where the hardware computes it natively."""

from __future__ import annotations

import pytest
import torch

from studio.model import precision
from studio.model.precision import bf16_is_native, resolve_precision


def test_auto_follows_what_the_cpu_computes_natively(monkeypatch):
    monkeypatch.setattr(precision, "bf16_is_native", lambda device="cpu": True)
    assert resolve_precision("auto") == "bf16"
    monkeypatch.setattr(precision, "bf16_is_native", lambda device="cpu": False)
    assert resolve_precision("auto") == "fp32"
    # An explicit choice is kept whatever the hardware.
    assert resolve_precision("bf16") == "bf16" and resolve_precision("fp32") == "fp32"


def test_this_machine_answers_from_onednn_and_other_devices_are_not_guessed():
    assert bf16_is_native("cpu") == bool(
        torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    )
    assert bf16_is_native("meta") is False


def test_an_unknown_precision_is_named():
    with pytest.raises(ValueError, match="one of auto, fp32, bf16, got 'fp16'"):
        resolve_precision("fp16")
