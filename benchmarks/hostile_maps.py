"""Crafted maps against genuine ones of the same file size: time and peak memory of `mapdb info` and `query`.

The "long" cases of the hostile-map suite (``tests/test_hostile_maps.py`` has the fast ones and the
generator used here):

* **pile on one spot**: what the old writer made of millions of objects at one position (the issue's
  1.16 MB map with 4.2 million objects took over ten minutes to query); now refused when opened;
* **pages piled on one spot**: pages of 255 objects (one per label, which a page may hold whatever its
  area), all on one position; refused when opened (pages may not overlap);
* **max-density lattice**: the valid map with the most objects per byte (one label on a 1 km lattice at a
  quantum of 1 km: 3 bits an object), written by ``write_map`` itself;
* **max-density 0.1 m**: random objects at the density limit (one per square metre) at 0.1 m;
* **tiny pages**: one object a page (``page_capacity=1``), the most pages a file of that size can hold;
* **hostile 65,535-object page**: a page at the count limit whose last object repeats a position, so that
  the error comes at the very end of decoding it.

Each is compared with a genuine map of about the same size: Andorra built from the real extract (27 KB),
and, for the 1.16 MB tier, 400,000 random objects written by ``write_map`` (2.98 bytes an object, like a
dense city).  Every command runs in a fresh process (``python -m mapdb_cli``) under GNU time, which gives
its peak memory (maximum resident set); times include the interpreter's start, about 0.6 s.

The 1.16 MB tier queries with a prior only (each image carries one of 300 m), and the valid hostile maps
of millions of objects get ``info`` only: a whole-map query indexes every object (about 19 KB an object in
the fast matcher, see the 27 KB tier), some 7 GB for the genuine map and 40 GB for the lattice.

Usage: ``python3 benchmarks/hostile_maps.py [--workdir DIR]`` (needs ``../shared/data`` for Andorra).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from test_hostile_maps import DIR, Page, Parts, Run, encode_page, handmade  # noqa: E402

from mapdb import Objects  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.mapfile.writer import write_map  # noqa: E402
from mapdb.simulation.simulate import simulate_images  # noqa: E402

ANDORRA = ROOT.parent / "shared" / "data" / "osm" / "andorra-2021-06-22.osm.pbf"
CRS = "EPSG:32631"
X0, Y0 = 380000.0, 4700000.0


def run(*args: str) -> tuple[float, float, int, str]:
    """Seconds, peak MB, exit status and the error line of ``mapdb ARGS`` in a fresh process.

    Peak memory is GNU time's maximum resident set of the command alone (``wait4`` on a child forked from
    this process would count this process's own memory, shared before the exec).
    """
    start = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-f", "%M", sys.executable, "-m", "mapdb_cli", *args],
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - start
    lines = proc.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("mapdb: error: ")]
    return seconds, int(lines[-1]) / 1024.0, proc.returncode, errors[-1] if errors else ""


def save_images(map_path: Path, out: Path, n: int = 3, **camera: float) -> Path:
    with open_map(map_path) as m:
        images = simulate_images(m, n, min_objects=6, seed=1, **camera)
    out.write_text("".join(json.dumps(im) + "\n" for im in images))
    return out


def sized(make, target: int, n0: int) -> tuple[Path, int]:
    """``make(n)`` with n scaled so that the file is about ``target`` bytes (two tries)."""
    path = make(n0)
    n = max(1, int(n0 * target / path.stat().st_size))
    return make(n), n


def pile_on_one_spot(path: Path, n: int) -> Path:
    """The old writer's pile: n buildings at one position, chopped into pages of 65,535 (key gaps of 0)."""
    full = encode_page([Run(0, [0] * 65535, [0] * 65535)], 0, 0)
    sizes = [65535] * (n // 65535) + ([n % 65535] if n % 65535 else [])
    payloads = [full if s == 65535 else encode_page([Run(0, [0] * s, [0] * s)], 0, 0) for s in sizes]
    return write_parts(path, pages_at_one_spot(payloads, sizes, ("building",)))


def pages_piled(path: Path, n_pages: int) -> Path:
    """n pages each holding one object of each of 255 labels, all at one position."""
    labels = tuple(f"label{i}" for i in range(255))
    payload = encode_page([Run(c, [0]) for c in range(255)], 0, 0)
    return write_parts(path, pages_at_one_spot([payload] * n_pages, [255] * n_pages, labels))


def pages_at_one_spot(payloads: list[bytes], counts: list[int], labels: tuple[str, ...]) -> Parts:
    parts = handmade([Page(int(X0 / 0.1), int(Y0 / 0.1), 0, 0, [Run(0, [0])])], labels=labels)
    parts.payloads = payloads
    parts.table = np.array([(int(X0 / 0.1), int(Y0 / 0.1), 0, 0, c, 0, 0) for c in counts], DIR)
    total = int(sum(counts))
    parts.header["count"] = total
    for entry in parts.header["labels"]:
        entry["count"] = total if len(labels) == 1 else total // len(labels)
    return parts


def write_parts(path: Path, parts: Parts) -> Path:
    path.write_bytes(parts.to_bytes())
    return path


def lattice(path: Path, n: int, spacing: float = 1000.0) -> Path:
    side = max(2, int(np.sqrt(n)))
    gx, gy = np.meshgrid(np.arange(side), np.arange(side))
    o = Objects(300000.0 + gx.ravel() * spacing, 4.6e6 + gy.ravel() * spacing, np.zeros(side * side, int),
                np.zeros(side * side), ("building",), CRS)
    write_map(path, o, quantum=spacing)
    return path


def dense_random(path: Path, n: int) -> Path:
    """n random buildings at one per square metre, quantum 0.1 m (the writer keeps every page within the rule)."""
    rng = np.random.default_rng(2)
    side = np.sqrt(n)
    o = Objects(X0 + rng.uniform(0, side, n), Y0 + rng.uniform(0, side, n), np.zeros(n, int),
                rng.lognormal(4, 1, n), ("building",), CRS)
    write_map(path, o)
    return path


def genuine_random(path: Path, n: int) -> Path:
    rng = np.random.default_rng(0)
    o = Objects(X0 + rng.uniform(0, 8000, n), Y0 + rng.uniform(0, 5000, n), rng.integers(0, 4, n),
                rng.lognormal(5, 1.5, n), ("building", "road_intersection", "park", "water"), CRS)
    write_map(path, o)
    return path


def tiny_pages(path: Path, n: int) -> Path:
    rng = np.random.default_rng(4)
    o = Objects(X0 + rng.uniform(0, 8000, n), Y0 + rng.uniform(0, 5000, n), rng.integers(0, 4, n),
                rng.lognormal(5, 1.5, n), ("building", "road_intersection", "park", "water"), CRS)
    write_map(path, o, page_capacity=1)
    return path


def big_page(path: Path, hostile: bool) -> Path:
    """One page of 65,535 buildings over 256 x 256 m at 0.1 m (the count and density limits)."""
    ex = ey = 2559
    keys = [i * 100 for i in range(65534)] + [(ex + 1) * (ey + 1) - 1]
    if hostile:
        keys[-2] = keys[-3]  # two objects of one label at one position, found at the end of the page
    return write_parts(path, handmade([Page(int(X0 / 0.1), int(Y0 / 0.1), ex, ey, [Run(0, keys)])],
                                      labels=("building",)))


def header_count(path: Path) -> str:
    try:
        with open_map(path) as m:
            return f"{len(m):,}"
    except Exception:  # a refused map: read the claim from the raw header
        import struct
        import zlib

        data = path.read_bytes()
        length = struct.unpack_from("<I", data, 12)[0]
        return f"{json.loads(zlib.decompress(data[16 : 16 + length], -15))['count']:,} (claimed)"


def page_decode(path: Path, page: int = 0) -> tuple[float, float, str]:
    """In-process: ms and peak MB (tracemalloc) to read and decode one page, and how it ended."""
    with open_map(path) as m:
        tracemalloc.start()
        start = time.perf_counter()
        try:
            n = m._page(page)[2].size
            outcome = f"{n} objects"
        except Exception as exc:  # noqa: BLE001 - the hostile page's one-line error is the outcome
            outcome = str(exc).split(": ", 1)[-1]
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return seconds * 1000.0, peak / 2**20, outcome


Row = tuple[str, str, int, Any, Any, Any]


def small_tier(work: Path, measure: Callable[[str, str, Path, Path | None], None]) -> tuple[Path, Path]:
    """Tier 1, maps the size of Andorra's: the genuine map and its hostile twins.  The valid and hostile
    65,535-object pages, for the in-process page decode."""
    andorra = work / "andorra.mapdb"
    subprocess.run([sys.executable, "-m", "mapdb_cli", "build", str(ANDORRA), "-o", str(andorra), "--overwrite"],
                   check=True, capture_output=True)
    size = andorra.stat().st_size
    images = save_images(andorra, work / "andorra.jsonl")
    measure("27 KB", "genuine: Andorra", andorra, images)
    pile, _ = sized(lambda n: pile_on_one_spot(work / "pile.mapdb", n), size, 100_000)
    measure("27 KB", "pile on one spot", pile, images)
    piled, _ = sized(lambda n: pages_piled(work / "piled.mapdb", n), size, 20)
    measure("27 KB", "pages piled on one spot", piled, images)
    lat, _ = sized(lambda n: lattice(work / "lattice.mapdb", n), size, 60_000)
    measure("27 KB", "max-density lattice (valid)", lat, save_images(lat, work / "lattice.jsonl", altitude=8000.0))
    dense, _ = sized(lambda n: dense_random(work / "dense.mapdb", n), size, 20_000)
    measure("27 KB", "max-density 0.1 m (valid)", dense, save_images(dense, work / "dense.jsonl", altitude=12.0))
    tiny, _ = sized(lambda n: tiny_pages(work / "tiny.mapdb", n), size, 600)
    measure("27 KB", "tiny pages (valid)", tiny, images)
    page_ok, page_bad = big_page(work / "page_ok.mapdb", False), big_page(work / "page_bad.mapdb", True)
    measure("27 KB", "65,535-object page (valid)", page_ok, save_images(page_ok, work / "page.jsonl", altitude=12.0))
    measure("27 KB", "65,535-object page (hostile)", page_bad, work / "page.jsonl")
    return page_ok, page_bad


def large_tier(work: Path, measure: Callable[[str, str, Path, Path | None], None]) -> Path:
    """Tier 2, maps the size of the issue's 1.16 MB map.  The genuine map, for the in-process page decode."""
    target = 1_160_000
    # Queries with a prior of 300 m (carried by each image), so that only the tiles around it are indexed.
    genuine, _ = sized(lambda n: genuine_random(work / "genuine_big.mapdb", n), target, 400_000)
    big_images = save_images(genuine, work / "genuine_big.jsonl", altitude=100.0, with_prior=300.0)
    measure("1.16 MB", "genuine: 400k random (prior)", genuine, big_images)
    measure("1.16 MB", "pile on one spot", pile_on_one_spot(work / "pile_big.mapdb", 4_200_000), big_images)
    piled_big, _ = sized(lambda n: pages_piled(work / "piled_big.mapdb", n), target, 800)
    measure("1.16 MB", "pages piled on one spot", piled_big, big_images)
    # A valid map of millions of objects: `info` only.  Its query indexes the whole map (an image of a 1 km
    # lattice spans kilometres, past the reach of a tile block), some 40 GB for the matcher, as a genuine map
    # of that many objects would; the 27 KB tier measures that cost per object.
    lat_big, _ = sized(lambda n: lattice(work / "lattice_big.mapdb", n), target, 2_000_000)
    measure("1.16 MB", "max-density lattice (info only)", lat_big, None)
    dense_big, _ = sized(lambda n: dense_random(work / "dense_big.mapdb", n), target, 900_000)
    measure("1.16 MB", "max-density 0.1 m (info only)", dense_big, None)
    tiny_big, _ = sized(lambda n: tiny_pages(work / "tiny_big.mapdb", n), target, 25_000)
    measure("1.16 MB", "tiny pages (prior)", tiny_big, big_images)
    return genuine


def print_rows(rows: list[Row], work: Path) -> None:
    """The table: each map's times and memory beside its tier's genuine map."""
    print(f"work directory: {work}\n")
    print(f"{'tier':8} {'map':34} {'bytes':>9} {'objects':>22} | {'info s':>7} {'MB':>6} {'x time':>6} {'x mem':>6} |"
          f" {'query s':>7} {'MB':>6} {'x time':>6} {'x mem':>6} | outcome")
    base: dict[str, tuple] = {}
    for tier, name, nbytes, count, info, query in rows:
        if name.startswith("genuine"):
            base[tier] = (info, query)
        g_info, g_query = base[tier]
        cells = []
        for got, ref in ((info, g_info), (query, g_query)):
            if got is None:
                cells.append(f"{'-':>7} {'-':>6} {'-':>6} {'-':>6}")
            else:
                cells.append(f"{got[0]:7.2f} {got[1]:6.0f} {got[0] / ref[0]:6.2f} {got[1] / ref[1]:6.2f}")
        status = [r for r in (info, query) if r is not None]
        outcome = "ok" if all(r[2] == 0 for r in status) else next(r[3] for r in status if r[2] != 0)
        outcome = outcome.replace(str(work) + "/", "")
        print(f"{tier:8} {name:34} {nbytes:9,} {count:>22} | {cells[0]} | {cells[1]} | {outcome[:90]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    if not ANDORRA.exists():
        sys.exit(f"{ANDORRA} is absent: this benchmark compares with the Andorra extract (../shared/data)")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="hostile_maps."))
    work.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []

    def measure(tier: str, name: str, path: Path, images: Path | None) -> None:
        info = run("info", str(path))
        query = run("query", str(path), str(images)) if images else None
        rows.append((tier, name, path.stat().st_size, header_count(path), info, query))

    page_ok, page_bad = small_tier(work, measure)
    genuine = large_tier(work, measure)
    print_rows(rows, work)
    print("\nOne page read and decoded in-process (tracemalloc peak):")
    genuine_page = page_decode(genuine)
    for name, path in (("genuine page (400k map)", genuine), ("65,535-object page (valid)", page_ok),
                       ("65,535-object page (hostile)", page_bad)):
        ms, mb, outcome = page_decode(path) if path != genuine else genuine_page
        print(f"  {name:30} {ms:8.1f} ms {mb:7.2f} MB  {outcome}")


if __name__ == "__main__":
    main()
