"""Start-up: what a process imports to answer one image, the quiet scipy loads, the quick schema check.

Timing lives in ``benchmarks/matcher_core.py``; these tests check the module sets that make it fast, in fresh
interpreters (a test session has imported everything already).
"""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from mapdb._scipy import StandIn
from mapdb.detections._quick_schema import surely_valid
from mapdb.detections.images import image_schema

# Imported by the packages the matcher avoids (scipy.spatial's __init__ loads scipy.sparse, linalg, special;
# scipy's array-API layer imports numpy.f2py and numpy.testing).
HEAVY = ["scipy.spatial", "scipy.special", "scipy.sparse", "scipy.linalg", "scipy._lib._array_api", "numpy.f2py",
         "numpy.testing", "jsonschema"]


def _python(code: str, *args: str, cwd: Path | None = None) -> str:
    """Run ``code`` in a fresh interpreter; its standard output."""
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, text=True,
                          cwd=cwd)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_the_matcher_imports_no_heavy_scipy_package() -> None:
    out = _python(f"""
        import json, sys
        import mapdb.localize.localizer
        print(json.dumps([[m for m in {HEAVY!r} if m in sys.modules],
                          [m for m in ("scipy.spatial._ckdtree", "scipy.special._ufuncs") if m in sys.modules]]))
    """)
    heavy, quiet = json.loads(out)
    assert heavy == []
    assert quiet == ["scipy.spatial._ckdtree", "scipy.special._ufuncs"]


def test_help_imports_no_numpy() -> None:
    out = _python("""
        import sys
        from mapdb_cli.main import cli
        cli(["--help"], standalone_mode=False)
        print("numpy" in sys.modules, "mapdb_cli.query" in sys.modules)
    """)
    assert out.splitlines()[-1] == "False False"


def test_the_mapdb_script_s_help_imports_no_numpy_scipy_or_kernel() -> None:
    # The console script's own path (python -m mapdb_cli is what it runs), ended by --help's exit.
    out = _python("""
        import atexit, json, runpy, sys
        atexit.register(lambda: print(json.dumps(sorted(
            m for m in sys.modules if m.split(".")[0] in ("numpy", "scipy", "numba", "shapely", "pyproj")))))
        sys.argv = ["mapdb", "--help"]
        runpy.run_module("mapdb_cli", run_name="__main__")
    """)
    assert "Usage: mapdb" in out
    assert json.loads(out.splitlines()[-1]) == []


def test_a_one_image_query_with_a_prior_loads_only_what_it_uses(paper_setup, tmp_path: Path) -> None:
    map_path, images = paper_setup
    image = {**images[0], "prior": {"x": images[0]["truth"]["x"], "y": images[0]["truth"]["y"], "radius": 300.0}}
    image_path = tmp_path / "one.jsonl"
    image_path.write_text(json.dumps(image) + "\n")
    # scipy.sparse (and with it scipy's array-API layer) comes in only when the final assignment has rivals to
    # settle (about 1 answer in 100); scipy.linalg, which scipy.sparse.csgraph's package would bring, never.
    with_sparse = ["scipy.sparse", "scipy._lib._array_api", "numpy.f2py", "numpy.testing"]
    out = _python(f"""
        import json, sys
        import mapdb.match.refine as refine
        ran = []
        matching = refine.min_weight_full_bipartite_matching
        refine.min_weight_full_bipartite_matching = lambda *a, **k: ran.append(1) or matching(*a, **k)
        from mapdb_cli.main import cli
        cli(["query", sys.argv[1], sys.argv[2]], standalone_mode=False)
        print(json.dumps([m for m in {HEAVY!r} if m in sys.modules and not (ran and m in {with_sparse!r})]))
    """, str(map_path), str(image_path))
    answer, loaded = (json.loads(line) for line in out.splitlines())
    assert answer["status"] == "ok"
    assert math.hypot(answer["x"] - image["truth"]["x"], answer["y"] - image["truth"]["y"]) < 5.0
    assert loaded == []


# What a one-image query with a prior never needs, each some 0.01-0.1 s of its start-up: numpy.ma (numpy 2's
# np.unique imports it on its first plain call), the paper's matcher, the stored index's reader and writer
# (multiprocessing), the label files' TOML parser.
NOT_FOR_ONE_ANSWER = ["numpy.ma", "mapdb.match.paper.algorithm", "mapdb.match.index.stored", "multiprocessing",
                      "tomllib"]


def test_a_one_image_query_with_a_prior_skips_what_it_never_needs(paper_setup, tmp_path: Path) -> None:
    map_path, images = paper_setup
    lines = [json.dumps({**image, "prior": {"x": image["truth"]["x"], "y": image["truth"]["y"], "radius": 300.0}})
             for image in images[:2]]  # the third's final assignment has rivals: scipy.sparse brings numpy.ma
    (tmp_path / "two.jsonl").write_text("\n".join(lines) + "\n")
    out = _python(f"""
        import json, sys
        from mapdb_cli.main import cli
        cli(["query", sys.argv[1], sys.argv[2]], standalone_mode=False)
        print(json.dumps([m for m in {NOT_FOR_ONE_ANSWER!r} if m in sys.modules]))
    """, str(map_path), str(tmp_path / "two.jsonl"))
    *answers, loaded = (json.loads(line) for line in out.splitlines())
    assert [a["status"] for a in answers] == ["ok"] * 2
    assert loaded == []


def test_the_quietly_loaded_objects_are_scipy_s_own() -> None:
    out = _python("""
        import numpy as np
        import mapdb._scipy as quiet
        import scipy.spatial, scipy.special, scipy._lib._util, scipy.sparse.csgraph
        from scipy.spatial import _ckdtree
        tree = quiet.cKDTree(np.random.default_rng(0).random((50, 2)))
        cost = np.array([[1.0, 2.0], [1.5, 9.0]])
        print(scipy.spatial.cKDTree is quiet.cKDTree, scipy.special.betainc is quiet.betainc,
              _ckdtree.copy_if_needed is scipy._lib._util.copy_if_needed,
              tree.sparse_distance_matrix(tree, 0.2).nnz > 0,  # its scipy.sparse is the real one
              scipy.sparse.csgraph.min_weight_full_bipartite_matching(scipy.sparse.csr_array(cost))[1].tolist()
              == quiet.min_weight_full_bipartite_matching(quiet.csr_array(cost))[1].tolist() == [1, 0])
    """)
    assert out.split() == ["True"] * 5


PACKAGE = {
    "pkg/__init__.py": "",
    "pkg/heavy.py": "VALUE = 'real'\n",
    "pkg/sub/__init__.py": "import sys\nsys.modules['pkg'].sub_init_ran = True\n",
    "pkg/sub/sibling.py": "X = 1\n",
    # Looks pkg.heavy up only when called, like scipy.spatial._ckdtree's scipy.sparse.
    "pkg/sub/good.py": "import pkg.heavy\nfrom . import sibling\ndef value():\n    return pkg.heavy.VALUE\n",
    "pkg/sub/wants_a_name.py": "from pkg.heavy import VALUE\n",  # a stand-in without VALUE cannot serve it
    "pkg/sub/keeps_it.py": "import pkg.heavy as heavy\n",  # would keep the stand-in itself
}


@pytest.fixture()
def package(tmp_path: Path) -> Path:
    for name, text in PACKAGE.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    return tmp_path


@pytest.mark.parametrize("module, quiet", [("good", True), ("wants_a_name", False), ("keeps_it", False)])
def test_load_quietly_skips_the_package_init_or_leaves_the_normal_import(package: Path, module: str,
                                                                         quiet: bool) -> None:
    out = _python(f"""
        import json, sys
        sys.path.insert(0, ".")
        from mapdb._scipy import load_quietly
        ok = load_quietly("pkg.sub.{module}", stand_ins={{"pkg.heavy": {{}}}})
        state = [ok, "pkg.sub" in sys.modules, "pkg.heavy" in sys.modules, "pkg.sub.{module}" in sys.modules,
                 hasattr(sys.modules["pkg"], "sub_init_ran")]
        from pkg.sub import {module} as m  # the normal import: runs pkg/sub/__init__.py, reuses a quiet load
        import pkg.heavy
        state += [hasattr(sys.modules["pkg"], "sub_init_ran"), getattr(m, "heavy", pkg.heavy) is pkg.heavy]
        print(json.dumps(state))
    """, cwd=package)
    ok, sub_loaded, heavy_loaded, module_loaded, init_ran, init_ran_later, real_heavy = json.loads(out)
    assert ok is quiet and module_loaded is quiet
    assert not sub_loaded and not heavy_loaded and not init_ran  # no bare package or stand-in left behind
    assert init_ran_later and real_heavy


def test_a_stand_in_lends_the_real_module_s_attributes_only_once_out_of_sys_modules(monkeypatch) -> None:
    stand_in = StandIn("json")
    stand_in.loads = "its own"
    assert stand_in.dumps is json.dumps and stand_in.loads == "its own"
    monkeypatch.setitem(sys.modules, "json", stand_in)  # as during a quiet load
    with pytest.raises(AttributeError):
        stand_in.dumps  # noqa: B018 - the attribute access is the test
    with pytest.raises(AttributeError):
        StandIn("json").__path__  # noqa: B018 - nor dunders, which the import system probes


def _mutations(doc: dict, rng: random.Random) -> list[dict]:
    """Valid and invalid variants of an image document, near the schema's edges."""
    odd = [None, True, False, "7", "", [], {}, -1, 0, 0.0005, 1, 179.9, 180, 1e6, 1e6 + 1, 2e7, 2e7 + 1, 1e8 + 1,
           -91, 89.5, math.nan, math.inf, -math.inf, np.float64(5.0), 3.0, 10**400]
    keys = ["id", "width", "height", "objects", "prior", "attitude", "camera", "altitude_m", "truth"]
    out = []
    for key in keys:
        out.append({k: v for k, v in doc.items() if k != key})
        out += [{**doc, key: value} for value in rng.sample(odd, 6)]
    for part, fields in (("prior", ["x", "y", "lon", "lat", "radius"]), ("attitude", ["roll_deg", "pitch_deg"]),
                         ("camera", ["fov_deg"])):
        for _ in range(12):
            chosen = rng.sample(fields, rng.randint(0, len(fields)))
            out.append({**doc, part: {f: rng.choice(odd + [0.5, 100.0, 42.0]) for f in chosen}})
    objects = doc["objects"]
    for _ in range(20):
        bad = dict(rng.choice(objects))
        bad[rng.choice(["label", "x", "y", "area_px", "border", "bbox", "box", "extra"])] = rng.choice(
            odd + [[1, 2, 3, 4], [1, 2, 3], [1, 2, 3, -4], "road"])
        out.append({**doc, "objects": [*objects, bad]})
    out.append({**doc, "objects": objects * (20001 // len(objects) + 1)})  # too many
    return out


def test_quick_schema_says_valid_only_when_jsonschema_agrees(paper_setup) -> None:
    _, images = paper_setup
    schema = image_schema()
    judge = Draft202012Validator(schema)
    rng = random.Random(5)
    base = {**images[0], "prior": {"x": 1.0, "y": 2.0, "radius": 300.0}, "attitude": {"roll_deg": 1.0},
            "camera": {"fov_deg": 60.0}, "altitude_m": 100.0}
    docs = [doc for image in images for doc in (image, base)]
    docs += [m for doc in docs for m in _mutations(doc, rng)]
    verdicts = [(surely_valid(schema, d), not any(True for _ in judge.iter_errors(d))) for d in docs]
    assert all(valid for quick, valid in verdicts if quick)  # a quick "valid" is never wrong
    assert all(quick for quick, _ in verdicts[: 2 * len(images)])  # the plain documents take the quick path
    quick_yes = sum(q for q, _ in verdicts)
    valid = sum(v for _, v in verdicts)
    assert 0 < quick_yes <= valid < len(verdicts)  # the mutations reach both sides of the schema
    assert valid - quick_yes < 0.2 * valid  # and only odd values (numpy numbers, 3.0 as an id) fall through


def test_a_build_of_osm_extracts_imports_no_raster_reader() -> None:
    """rasterio and scipy.ndimage (0.3-0.6 s) load only when a build reads a raster."""
    out = _python("""
        import sys
        import mapdb.build.pipeline, mapdb.sources
        print(mapdb.sources.source_kind("clc.tif"), "rasterio" in sys.modules, "scipy.ndimage" in sys.modules)
    """)
    assert out.split() == ["landcover", "False", "False"]


def test_a_lost_in_space_answer_from_the_stored_index_does_not_import_numpy_ma(paper_setup, tmp_path: Path) -> None:
    """The stored index's lookups (its blocks checked, its label combinations audited) use
    :func:`mapdb.match.arrays.sorted_unique`, not ``np.unique``/``setdiff1d``/``union1d``, whose plain call imports
    numpy.ma: 0.03 of a first answer's 0.06 s of CPU on Andorra (``benchmarks/diagnostics/first_answers.py``)."""
    map_path, images = paper_setup
    indexed = tmp_path / "indexed.mapdb"
    indexed.write_bytes(map_path.read_bytes())
    from mapdb.match.index.stored import build_index

    build_index(indexed)
    (tmp_path / "two.jsonl").write_text("\n".join(json.dumps(image) for image in images[:2]) + "\n")
    out = _python("""
        import json, sys
        from mapdb_cli.main import cli
        cli(["query", sys.argv[1], sys.argv[2]], standalone_mode=False)
        print(json.dumps(["numpy.ma" in sys.modules, "mapdb.match.index.stored" in sys.modules]))
    """, str(indexed), str(tmp_path / "two.jsonl"))
    *answers, loaded = (json.loads(line) for line in out.splitlines())
    assert [a["status"] for a in answers] == ["ok"] * 2
    assert loaded == [False, True]  # the stored index answered, and numpy.ma stayed out
