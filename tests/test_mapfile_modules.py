"""The map file package's shape (issue 27): one concept a module, and the public API still where the README names
it (``mapdb.store``).  Module sizes and import cycles are checked for the whole tree by ``test_layout.py``."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mapdb" / "mapfile"


def _modules() -> dict[str, Path]:
    return {p.stem: p for p in sorted(PACKAGE.glob("*.py")) if p.stem != "__init__"}


def test_the_old_single_module_is_gone() -> None:
    modules = _modules()
    assert "store" not in modules
    assert {"layout", "codec", "pages", "spill", "header", "writer", "queries", "reader"} <= set(modules)


@pytest.mark.parametrize("name", sorted(_modules()))
def test_every_module_names_its_public_api(name: str) -> None:
    module = importlib.import_module(f"mapdb.mapfile.{name}")
    assert isinstance(module.__all__, list)
    assert all(hasattr(module, item) for item in module.__all__)


def test_the_public_api_is_still_mapdb_store() -> None:
    import mapdb.store as public

    assert set(public.__all__) == {"DEFAULT_MEMORY_OBJECTS", "DEFAULT_QUANTUM", "FORMAT_VERSION", "MAGIC", "MapBase",
                                   "MapWriter", "MemoryMap", "MetaMap", "area_codes", "open_map", "write_map",
                                   "write_map_from_chunks"}
    for item in public.__all__:
        home = getattr(public, item)
        owners = [name for name in _modules() if item in importlib.import_module(f"mapdb.mapfile.{name}").__all__]
        assert len(owners) == 1, f"{item} should have one home, has {owners}"
        assert getattr(importlib.import_module(f"mapdb.mapfile.{owners[0]}"), item) is home
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("mapdb.mapfile.store")
