"""Decoding a plan's predicted latent trajectory into images, with the latent decoder of its checkpoint.

What the world model imagined, as images, for the inspector: the rollout and plan jobs and ``studio eval`` decode
here, where the model lives, so that viewers (the UI) never need torch. A checkpoint's decoder is found by
convention (:func:`find_decoder`): ``decoder/best.pt``, ``decoder/last.pt`` or ``decoder.pt`` next to the
checkpoint, or ``<stem>.decoder.pt``. Decoders are loaded once per process (keyed by file and modification time).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if (
    TYPE_CHECKING
):  # the rollout module loads the simulator; this one stays light (the UI's plan job imports it)
    from studio.eval.rollout import PlanRecord

_DECODERS: dict[str, Any] = {}


def find_decoder(checkpoint: str | os.PathLike) -> Path | None:
    """The latent decoder belonging to ``checkpoint`` (see the module docstring), or None."""
    ck = Path(checkpoint)
    for cand in (
        ck.parent / "decoder" / "best.pt",
        ck.parent / "decoder" / "last.pt",
        ck.parent / "decoder.pt",
        ck.with_name(f"{ck.stem}.decoder.pt"),
    ):
        if cand.is_file():
            return cand
    return None


def decode_latents(checkpoint: str | os.PathLike, pooled_states: np.ndarray) -> np.ndarray | None:
    """(S, D) pooled latent states → (S, h, w, 3) uint8 images with the checkpoint's decoder (None: none)."""
    path = find_decoder(checkpoint)
    if path is None:
        return None
    key = f"{path}:{path.stat().st_mtime_ns}"
    if key not in _DECODERS:
        from studio.model.train_decoder import load_decoder

        _DECODERS[key] = load_decoder(path)
    decoder = _DECODERS[key]
    pooled = np.asarray(pooled_states, dtype=np.float32)
    if pooled.ndim != 2 or pooled.shape[1] != decoder.in_dim:
        raise ValueError(
            f"decoder {path} reads ({decoder.in_dim},) pooled states, got an array of shape {pooled.shape}"
        )
    return decoder.render(pooled)


def attach_latent_images(checkpoint: str | os.PathLike, plans: Iterable[PlanRecord]) -> None:
    """Set ``latent_images`` on every plan that kept its pooled states, when the checkpoint has a decoder."""
    for p in plans:
        if p.pooled_states is not None:
            p.latent_images = decode_latents(checkpoint, p.pooled_states)
