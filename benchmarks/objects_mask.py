"""Masks to objects: time and peak memory of ``from_mask`` on a 4000x3000 mask, and of ``mapdb objects`` on its PNG.

The mask is generated: about 500 objects (rectangles and ellipses of 10-120 px, three classes, some touching
so that they merge, some cut by the border) on a background of 0, plus 2 % of pixels of a class the table
does not map.  ``from_mask`` is timed in this process (median of 5, after one warm-up) with its peak
memory above the mask itself traced by ``tracemalloc`` (numpy reports its buffers to it); the command,
which also reads the PNG and writes the JSON, is timed as a fresh process with its peak RSS.

Run from the repository root::

    python benchmarks/objects_mask.py
"""

from __future__ import annotations

import resource
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 4000, 3000
CLASSES = {1: "building", 2: "water", 3: "park"}


def generated_mask(n: int, seed: int = 0) -> np.ndarray:
    """``n`` shapes of classes 1-3 at random places, and class 9 noise (skipped: not in the table)."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    rows, cols = np.ogrid[:HEIGHT, :WIDTH]
    for i in range(n):
        cx, cy = rng.uniform(-20, WIDTH + 20), rng.uniform(-20, HEIGHT + 20)
        w, h = rng.uniform(10, 120, 2)
        code = 1 + i % 3
        y0, y1, x0, x1 = (max(int(v), 0) for v in (cy - h / 2, cy + h / 2, cx - w / 2, cx + w / 2))
        if i % 2:
            mask[y0:y1, x0:x1] = code
        else:
            window = (slice(y0, y1), slice(x0, x1))
            inside = ((cols[:, window[1]] - cx) / (w / 2)) ** 2 + ((rows[window[0]] - cy) / (h / 2)) ** 2 <= 1
            mask[window][inside] = code
    noise = rng.random((HEIGHT, WIDTH)) < 0.02
    mask[noise & (mask == 0)] = 9
    return mask


def time_from_mask(mask: np.ndarray, classes: dict[int, str] = CLASSES, **options
                   ) -> tuple[float, float, float, int]:
    """Median wall and CPU seconds of 5 runs, traced peak MB, objects found."""
    from mapdb.detections.masks import from_mask

    from_mask(mask, classes, **options)  # warm-up: imports and first-touch allocations
    times, cpu = [], []
    for _ in range(5):
        start, start_cpu = time.perf_counter(), time.process_time()
        doc = from_mask(mask, classes, **options)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    tracemalloc.start()
    from_mask(mask, classes, **options)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return statistics.median(times), statistics.median(cpu), peak / 2**20, len(doc["objects"])


def time_command(png: Path, out: Path) -> tuple[float, float]:
    """Wall time and peak RSS of ``mapdb objects MASK.png`` in a fresh process."""
    code = ("import resource, sys; from mapdb_cli.main import cli\n"
            "try:\n    cli(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)")
    classes = out.with_suffix(".toml")
    classes.write_text("[classes]\n" + "".join(f'{k} = "{v}"\n' for k, v in CLASSES.items()))
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-c", code, "objects", str(png), "--classes", str(classes),
                             "-o", str(out), "-q"], capture_output=True, text=True, check=True)
    return time.perf_counter() - start, float(result.stdout.strip().splitlines()[-1])


def main() -> None:
    import rasterio

    print(f"{'case (from_mask unless said)':<44} {'objects':>7} {'wall s':>7} {'CPU s':>6} {'peak MB':>8}")
    mask = generated_mask(650)
    cases = [(mask, CLASSES, {}, "4000x3000, 3 classes, 8-connected"),
             (mask, CLASSES, {"connectivity": 4}, "4000x3000, 3 classes, 4-connected"),
             (mask == 1, {1: "building"}, {}, "4000x3000, one class (a 0/255 mask)"),
             (generated_mask(6500), CLASSES, {}, "4000x3000, 3 classes, ten times the shapes")]
    for array, classes, options, name in cases:
        seconds, cpu, peak, found = time_from_mask(array, classes, **options)
        print(f"{name:<44} {found:>7} {seconds:>7.3f} {cpu:>6.3f} {peak:>8.0f}")
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "mask.png"
        with rasterio.open(png, "w", driver="PNG", width=WIDTH, height=HEIGHT, count=1, dtype="uint8") as ds:
            ds.write(mask, 1)
        seconds, rss = time_command(png, Path(tmp) / "images.jsonl")
        print(f"{'mapdb objects mask.png (whole process)':<44} {'':>7} {seconds:>7.3f} {'':>6} {rss:>8.0f}"
              "  (peak RSS)")
    print(f"this process's peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB; "
          f"the mask itself is {WIDTH * HEIGHT / 2**20:.0f} MB (uint8)")


if __name__ == "__main__":
    main()
