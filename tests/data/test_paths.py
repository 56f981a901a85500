"""Dataset root resolution: --data-dir beats STUDIO_DATA_DIR beats the user data directory."""

from __future__ import annotations

import argparse

from studio.data import paths


def test_explicit_value_wins(tmp_path, monkeypatch):
    monkeypatch.setenv(paths.ENV_VAR, str(tmp_path / "env"))
    assert paths.resolve_data_dir(tmp_path / "cli") == (tmp_path / "cli").resolve()


def test_environment_variable_used_without_cli(tmp_path, monkeypatch):
    monkeypatch.setenv(paths.ENV_VAR, str(tmp_path / "env"))
    assert paths.resolve_data_dir(None) == (tmp_path / "env").resolve()


def test_default_is_user_data_dir(monkeypatch):
    monkeypatch.delenv(paths.ENV_VAR, raising=False)
    root = paths.resolve_data_dir(None)
    assert root == paths.default_data_dir()
    assert paths.APP_NAME in str(root)


def test_argument_added():
    parser = argparse.ArgumentParser()
    paths.add_data_dir_argument(parser)
    assert parser.parse_args(["--data-dir", "/x"]).data_dir == "/x"
    assert parser.parse_args([]).data_dir is None
