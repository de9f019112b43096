"""Peak memory and time of ``mapdb query`` over long batches: memory stays flat as the input grows.

For each size (default 10,000 and 1,000,000 lines) a JSON Lines images file is generated over a
small paper-style map (:func:`mapdb.simulation.simulate.paper_map`), and ``mapdb query MAP FILE`` runs on it in
a child process whose answers are read from its stdout as they come.  Reported per run:

* lines in the file, non-blank lines, answers (must equal the non-blank lines), ok and rejected;
* peak RSS of the child (``ru_maxrss`` from ``os.wait4``), and its RSS sampled (psutil) when 10 %,
  50 % and 90 % of the answers had arrived: a reader that held its input would grow with the file;
* wall and CPU seconds of the child, and answers per second.

The lines are a fixed cycle of 100 so that the run is quick yet touches every path: 3 valid
simulated images (matched in full; two of them carry a raw U+2028 or U+0085 in their id), 60
images with labels the map does not have (4 to 8 objects), 15 with too few objects, 12 with
numbers out of range (a prior radius of 1e308, a raw ``NaN``, an altitude of 1e308, a field of
view of 180), 9 broken lines (malformed JSON, not UTF-8, a JSON array, a number, a raw form feed
inside a string, deep nesting, a 5000-digit number) and 1 blank line.

Two more rows bound what one line can cost: a line just under the 16 MiB line limit holding
tiny objects (rejected for having more than ``MAX_OBJECTS``), and a line over it (rejected unread).
A first row opens the map on an empty file: the floor of the interpreter, numpy, pyproj and
jsonschema.  Run (it takes a few minutes for the million lines; use ``nice`` on a shared machine)::

    nice python benchmarks/batch_memory.py [--lines 10000,1000000] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CYCLE = 100


def _cycle(images: list[dict]) -> list[bytes]:
    """The 100 lines repeated through the file (valid images taken in turn from ``images``)."""
    base = {k: v for k, v in images[0].items() if k != "truth"}
    few = [{"label": "building", "x": 10.0 * i, "y": 20.0} for i in range(2)]

    def unknown(n: int) -> dict:
        return {**base, "id": "unknown", "objects": [{"label": "crater", "x": 30.0 * i, "y": 40.0} for i in range(n)]}

    lines: list[bytes] = [b"VALID"]  # replaced by a valid image per cycle
    lines += [json.dumps(unknown(4 + i % 5)).encode() for i in range(60)]
    lines += [json.dumps({**base, "id": "few", "objects": few}).encode() for _ in range(15)]
    bad_numbers = [
        {**base, "id": "radius", "prior": {"x": 1.0, "y": 1.0, "radius": 1e308}},
        {**base, "id": "altitude", "altitude_m": 1e308},
        {**base, "id": "fov", "camera": {"fov_deg": 180}},
    ]
    lines += [json.dumps(bad_numbers[i % 3]).encode() for i in range(9)]
    lines += [json.dumps({**base, "id": "nan", "altitude_m": 12345.5}).encode().replace(b"12345.5", b"NaN")] * 3
    lines += [
        b'{"id": "broken", "width": 640,',
        b'{"id": "bytes \xff\xfe", "width": 640}',
        b"[1, 2, 3]",
        b"12345",
        json.dumps({**base, "id": "sep\u2028arator"}, ensure_ascii=False).encode(),
        json.dumps({**base, "id": "next\u0085line"}, ensure_ascii=False).encode(),
        json.dumps({**base, "id": "form-feed"}).encode().replace(b"form-feed", b"form\x0cfeed"),
        b"{}",
        b"null",
        b"[" * 5000 + b"]" * 5000,
        b'{"id": 1' + b"0" * 5000 + b"}",
    ]
    lines.append(b"")
    assert len(lines) == CYCLE, len(lines)
    return lines


def write_batch(path: Path, n_lines: int, images: list[dict]) -> int:
    """Write ``n_lines`` lines; return the number of non-blank ones."""
    cycle = _cycle(images)
    valid = [json.dumps({k: v for k, v in im.items() if k != "truth"}).encode() for im in images]
    non_blank = 0
    with open(path, "wb") as f:
        for i in range(n_lines):
            line = cycle[i % CYCLE]
            if line == b"VALID":
                line = valid[(i // CYCLE) % len(valid)]
            non_blank += bool(line.strip())
            f.write(line + b"\n")
    return non_blank


def run_query(map_path: Path, images_path: Path, expected: int) -> dict:
    """Run ``mapdb query`` in a child, counting its answers as they stream and sampling its RSS."""
    try:
        import psutil
    except ImportError:  # the peak from wait4 is still exact; only the samples need psutil
        psutil = None
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "mapdb_cli", "query", str(map_path), str(images_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    child = psutil.Process(proc.pid) if psutil else None
    marks = {max(1, round(expected * q)): q for q in (0.1, 0.5, 0.9)}
    samples: dict[float, int] = {}
    answers = ok = 0
    for line in proc.stdout:
        answers += 1
        ok += line.startswith(b'{"id":') and b'"status":"ok"' in line[:120]
        if child is not None and answers in marks:
            samples[marks[answers]] = child.memory_info().rss
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"mapdb query failed ({proc.returncode}): {err.decode(errors='replace').strip()}")
    return {"answers": answers, "ok": ok, "peak": usage.ru_maxrss * 1024, "samples": samples, "wall": wall,
            "cpu": usage.ru_utime + usage.ru_stime}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lines", default="10000,1000000", help="comma-separated batch sizes")
    parser.add_argument("--dir", type=Path, default=None, help="where to write the files (default a temp dir)")
    parser.add_argument("--no-long-lines", dest="long_lines", action="store_false",
                        help="skip the rows of one line at and over the line limit")
    args = parser.parse_args()

    from mapdb.detections.images import MAX_DOCUMENT_BYTES
    from mapdb.mapfile.queries import MemoryMap
    from mapdb.mapfile.writer import write_map
    from mapdb.simulation.simulate import paper_map, simulate_images

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        objects = paper_map(seed=2)
        map_path = root / "paper.mapdb"
        write_map(map_path, objects)
        images = simulate_images(MemoryMap(objects), 20, pixel_std=1.0, yaw="random", seed=3)

        rows = []
        empty = root / "empty.jsonl"
        empty.write_bytes(b"")
        rows.append(("(empty file: the floor)", 0, 0, 0, run_query(map_path, empty, 0)))
        for n in (int(v) for v in args.lines.split(",")):
            path = root / f"batch-{n}.jsonl"
            non_blank = write_batch(path, n, images)
            size = path.stat().st_size
            result = run_query(map_path, path, non_blank)
            path.unlink()
            rows.append((f"{n:,} lines", n, non_blank, size, result))
        if args.long_lines:
            tiny = b'{"label":"building","x":1,"y":1},'
            count = (MAX_DOCUMENT_BYTES - 100) // len(tiny)
            head = b'{"id":"at-limit","width":640,"height":480,"objects":['
            at_limit = head + tiny * count + b'{"label":"b","x":1,"y":1}]}'
            over = b'{"id":"over","objects":[' + tiny * (count + 100_000) + b"]}"
            for name, line in (("one line at the limit", at_limit), ("one line over the limit", over)):
                path = root / "long.jsonl"
                path.write_bytes(line + b"\n")
                rows.append((f"{name} ({len(line) / 2**20:.1f} MiB)", 1, 1, len(line) + 1,
                             run_query(map_path, path, 1)))

    header = (f"{'input':36s} {'MB':>7s} {'non-blank':>9s} {'answers':>9s} {'ok':>6s} {'peak RSS':>9s} "
              f"{'RSS@10%':>8s} {'RSS@50%':>8s} {'RSS@90%':>8s} {'wall s':>8s} {'cpu s':>8s} {'ans/s':>7s}")
    print(header)
    print("-" * len(header))
    for name, _n, non_blank, size, r in rows:
        s = r["samples"]
        rss = [f"{s[q] / 1e6:6.0f}MB" if q in s else f"{'':8s}" for q in (0.1, 0.5, 0.9)]
        rate = f"{r['answers'] / r['wall']:7.0f}" if r["answers"] else f"{'':7s}"
        print(f"{name:36s} {size / 1e6:7.1f} {non_blank:9,d} {r['answers']:9,d} {r['ok']:6,d} "
              f"{r['peak'] / 1e6:7.0f}MB {rss[0]} {rss[1]} {rss[2]} {r['wall']:8.1f} {r['cpu']:8.1f} {rate}")
    print()
    for name, _n, non_blank, _size, r in rows:
        if r["answers"] != non_blank:
            print(f"{name}: {r['answers']} answers for {non_blank} non-blank lines: MISMATCH")
    print("answers == non-blank lines in every run" if all(r["answers"] == nb for _, _, nb, _, r in rows) else "")


if __name__ == "__main__":
    main()
