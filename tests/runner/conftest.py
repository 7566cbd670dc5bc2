"""Fixtures for runner tests: a plugin site registering the test stages, CLI environments."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.runner.helpers import cli_env, make_plugin_site


@pytest.fixture(scope="session")
def plugin_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_plugin_site(tmp_path_factory.mktemp("site"))


@pytest.fixture
def env(plugin_site: Path, tmp_path: Path) -> dict[str, str]:
    """Environment for `python -m runner.cli` with the test stages and a fresh cache."""
    return cli_env(plugin_site, tmp_path / "cache")
