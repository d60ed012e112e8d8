"""Shared test fixtures.

The whole session uses one cache directory (``$EXPLOREGS_CACHE`` points into the session's
tmp dir), so ``builtin:tiny`` is generated once per session and no test writes to ~/.cache.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
"""Real captured scenes next to the repository (tests that use them skip when absent)."""


@pytest.fixture(scope="session", autouse=True)
def exploregs_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session's cache root (``$EXPLOREGS_CACHE``): built-in scenes, derived images."""
    root = tmp_path_factory.mktemp("exploregs-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("EXPLOREGS_CACHE", str(root))
        yield root


@pytest.fixture(scope="session")
def tiny_scene_dir(exploregs_cache: Path) -> Path:
    """Folder of the built-in ``tiny`` scene (COLMAP text + depths + masks), made once.

    Read-only by convention: tests that modify a dataset copy it first."""
    from exploregs_plugin.data.builtin import ensure_builtin

    return ensure_builtin("tiny", exploregs_cache / "scenes")


@pytest.fixture()
def tiny_dm(tiny_scene_dir: Path):
    """A fresh DataManager on ``builtin:tiny`` (the scene itself is cached for the session)."""
    from exploregs_plugin.data import DataManagerConfig

    return DataManagerConfig(data="builtin:tiny").setup()
