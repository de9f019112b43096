"""Masks and COCO files at the limits: wall time and peak memory of reading one, in a fresh process each.

Cases (generated in a temporary folder; the bombs are small files that decode to large images):

* ``normal``: a 4000x3000 mask of three classes and about 450 objects (``benchmarks/objects_mask.py``'s);
* ``solid``: a 10000x10000 PNG, all 255 but a frame (about 120 KB): one object of 100 M pixels;
* ``dots``: a 10000x10000 PNG of 2x2 dots every 4 pixels (about 145 KB): 6.25 M objects, refused (more
  than a query accepts) once counted;
* ``specks``: a 10000x10000 PNG of single pixels every 2 pixels: 25 M regions, every one under the
  minimum area: the most labels a mask of this size can hold;
* ``coco-1m``: a COCO file of one polygon of 1,000,000 vertices (about 40 MB);
* ``coco-3m``: one polygon of 3,000,000 vertices (about 130 MB): refused by the vertex cap;
* ``coco-scribbles``: 2,000 annotations of 200 random vertices each (self-crossing scribbles);
* ``coco-zeros``: a COCO file of the largest size read (``MAX_COCO_BYTES``) that is one list of zeros: the
  most Python objects JSON can make of that many bytes.

Each case runs ``mask_document`` (or ``from_coco``) and writes the JSON, in a child process that reports its
own peak RSS (``VmHWM``: ``ru_maxrss`` would count the parent's, which generates the images, as Linux keeps it
across fork and exec); "wall s" is the child's whole run, Python's start and imports included.  With
``--code DIR`` the child imports ``mapdb`` from DIR first (an older checkout, for a before/after table).

Run from the repository root::

    python benchmarks/mask_limits.py                      # every case
    python benchmarks/mask_limits.py normal solid         # some of them
    python benchmarks/mask_limits.py --code /tmp/old normal
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from objects_mask import generated_mask  # noqa: E402

SIDE = 10_000
CASES = ("normal", "solid", "dots", "specks", "coco-1m", "coco-3m", "coco-scribbles", "coco-zeros")

_CHILD = """
import json, resource, sys, time, traceback
sys.path[:0] = [p for p in sys.argv[4:5] if p]
kind, path, out = sys.argv[1:4]
start = time.perf_counter()
try:
    if kind == "coco":
        from mapdb.detections.coco import from_coco
        docs = from_coco(path, {"1": "building"})
    else:
        from mapdb.detections.masks import mask_document
        options = {"label": "building"} if kind == "label" else {"classes": {1: "building", 2: "water", 3: "park"}}
        docs = [mask_document(path, **options)]
    with open(out, "w") as f:
        for doc in docs:
            f.write(json.dumps(doc, allow_nan=False) + "\\n")
    outcome = f"{sum(len(d['objects']) for d in docs)} objects"
except Exception as exc:
    outcome = "refused: " + str(exc).split(": ", 1)[-1][:70]
try:  # this process's own peak: ru_maxrss would also count the parent's, inherited across fork and exec
    with open("/proc/self/status") as f:
        peak_kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
except (OSError, StopIteration):
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"seconds": time.perf_counter() - start, "outcome": outcome, "rss_mb": peak_kb / 1024}))
"""


def _png(path: Path, array: np.ndarray) -> Path:
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver="PNG", width=array.shape[1], height=array.shape[0], count=1,
                           dtype="uint8", zlevel=9) as ds:
            ds.write(array, 1)
    return path


def _bomb(kind: str) -> np.ndarray:
    mask = np.zeros((SIDE, SIDE), np.uint8)
    if kind == "solid":
        mask[1:-1, 1:-1] = 255
    elif kind == "dots":
        for dy in (0, 1):
            for dx in (0, 1):
                mask[dy::4, dx::4] = 255
    else:
        mask[::2, ::2] = 255
    return mask


def _coco(path: Path, polygons: list[np.ndarray]) -> Path:
    annotations = [{"id": i, "image_id": 1, "category_id": 1, "segmentation": [np.round(p, 3).ravel().tolist()]}
                   for i, p in enumerate(polygons)]
    path.write_text(json.dumps({"images": [{"id": 1, "width": 4000, "height": 3000}], "annotations": annotations}))
    return path


def make_case(name: str, folder: Path) -> tuple[str, Path]:
    """The child's kind (``classes``, ``label``, ``coco``) and the file of case ``name``."""
    rng = np.random.default_rng(0)
    if name == "normal":
        return "classes", _png(folder / "normal.png", generated_mask(500))
    if name in ("solid", "dots", "specks"):
        return "label", _png(folder / f"{name}.png", _bomb(name))
    if name in ("coco-1m", "coco-3m"):
        n = 1_000_000 if name == "coco-1m" else 3_000_000
        turn = np.linspace(0, 2 * np.pi, n, endpoint=False)
        radius = 1000 + 400 * rng.random(n)  # a star: simple, and as jagged as vertices can make it
        return "coco", _coco(folder / f"{name}.json", [np.c_[2000 + radius * np.cos(turn),
                                                              1500 + radius * np.sin(turn)]])
    if name == "coco-scribbles":
        return "coco", _coco(folder / "scribbles.json", [rng.random((200, 2)) * (4000, 3000) for _ in range(2000)])
    from mapdb.detections.coco import MAX_COCO_BYTES

    head = b'{"images": [{"id": 1, "width": 40, "height": 30}], "annotations": [], "padding": ['
    zeros = (MAX_COCO_BYTES - len(head) - 3) // 2
    path = folder / "zeros.json"
    with open(path, "wb") as f:
        f.write(head + b"0," * (zeros - 1) + b"0]}")
    return "coco", path


def run_case(kind: str, path: Path, code: str) -> dict[str, object]:
    """Seconds, peak RSS (MB) and outcome of reading ``path`` in a fresh process."""
    result = subprocess.run([sys.executable, "-c", _CHILD, kind, str(path), str(path.with_suffix(".jsonl")), code],
                            capture_output=True, text=True, timeout=900)
    if result.returncode:
        return {"seconds": float("nan"), "rss_mb": float("nan"), "outcome": f"exit {result.returncode}"}
    report: dict[str, object] = json.loads(result.stdout.strip().splitlines()[-1])
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", help=f"cases to run, of {', '.join(CASES)} (default: all)")
    parser.add_argument("--code", default="", help="import mapdb from this folder first (an older checkout)")
    args = parser.parse_args()
    unknown = set(args.cases) - set(CASES)
    if unknown:
        parser.error(f"unknown cases: {', '.join(sorted(unknown))}")
    print(f"{'case':<16} {'file KB':>8} {'wall s':>7} {'peak RSS MB':>12}  outcome")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases or CASES:
            kind, path = make_case(name, Path(tmp))
            size_kb = path.stat().st_size / 1024
            start = time.perf_counter()
            report = run_case(kind, path, args.code)
            wall = time.perf_counter() - start
            print(f"{name:<16} {size_kb:>8.0f} {wall:>7.1f} {float(report['rss_mb']):>12.0f}  {report['outcome']}",
                  flush=True)
            path.unlink()


if __name__ == "__main__":
    main()
