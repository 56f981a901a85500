"""Decoding a plan's latent trajectory: which decoder belongs to a checkpoint."""

from __future__ import annotations

from studio.eval.latents import find_decoder


def test_find_decoder_by_convention(tmp_path):
    ck = tmp_path / "run" / "best.pt"
    ck.parent.mkdir()
    ck.write_bytes(b"x")
    assert find_decoder(ck) is None
    (tmp_path / "run" / "best.decoder.pt").write_bytes(b"x")
    assert find_decoder(ck) == tmp_path / "run" / "best.decoder.pt"
    (tmp_path / "run" / "decoder").mkdir()
    (tmp_path / "run" / "decoder" / "best.pt").write_bytes(b"x")
    assert find_decoder(ck) == tmp_path / "run" / "decoder" / "best.pt"
