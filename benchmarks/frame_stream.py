"""Peak memory and time of ``mapdb navigate MAP -`` over long frame streams: memory stays flat as the stream grows.

A map is built from the sample extract (``sample_maps/helsinki.osm.pbf``) and a short flight simulated over
it (``mapdb simulate flight``).  For each size (default 10,000 and 1,000,000 lines) the frames are generated
on the fly into the pipe of a ``mapdb navigate MAP - --initial X,Y,R`` child (nothing is written to disk),
its records are read as they come.  The lines are a fixed cycle of 1,000, times increasing 0.01 s a line:

* 1 full simulated frame (20-30 objects: a map query and a frame-to-frame match);
* 899 frames of 2 objects with every sensor (too few for a query: the filter predicts, the frame points
  are levelled and the frame-to-frame match is tried);
* 60 frames whose sensors are NaN, +-1e308, 400-digit integers or of the wrong type;
* 15 with 3 objects of labels the map lacks, each frame its own labels (the label table must not grow);
* 10 frames out of time order, 5 whose time is 1e308;
* 9 broken lines (malformed JSON, not UTF-8, an array, deep nesting, a 5000-digit number) and 1 blank line.

Reported per run: lines, non-blank lines, records (must equal the non-blank lines), records with a position,
peak RSS of the child (``ru_maxrss`` from ``os.wait4``) and its RSS sampled (psutil) when 10 %, 50 % and 90 %
of the records had arrived, wall and CPU seconds, and lines per second.  A first row runs an empty stream:
the floor of the interpreter, numpy, scipy and pyproj.  Run (the million lines take many minutes; use
``nice`` on a shared machine)::

    nice python benchmarks/frame_stream.py [--lines 10000,1000000] [--particles 2000] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

CYCLE = 1000
STEP_S = 0.01
REPO = Path(__file__).resolve().parents[1]


def _mapdb(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "mapdb_cli", *args], check=True, stdout=subprocess.DEVNULL)


def _cycle(frames: list[dict]) -> list[tuple[str, object]]:
    """The cycle's lines as (kind, payload): a "frame" is stamped with the stream's time when written."""
    two = {k: v for k, v in frames[0].items() if k != "truth"}
    two["objects"] = two["objects"][:2]
    lines: list[tuple[str, object]] = [("full", None)] + [("frame", two)] * 899
    bad_values = [float("nan"), float("inf"), 1e308, -1e308, 10**400, "12", [1.0], {"v": 1}]
    fields = ("altitude_m", "imu_velocity_mps", "width", "id", "truth", "map_withheld")
    lines += [("frame", {**two, fields[i % 6]: bad_values[i % len(bad_values)]}) for i in range(60)]
    lines += [("strangers", None)] * 15
    lines += [("raw", json.dumps({**two, "time_s": 0.0}).encode())] * 10  # out of time order
    lines += [("raw", json.dumps({**two, "time_s": 1e308}).encode())] * 5
    broken = [b'{"id": "broken", "width": 640,', b'{"id": "bytes \xff\xfe"}', b"[1, 2, 3]", b"12345", b"{}",
              b"null", b"[" * 5000 + b"]" * 5000, b'{"id": 1' + b"0" * 5000 + b"}", b'{"time_s": 1e400}', b""]
    lines += [("raw", line) for line in broken]
    assert len(lines) == CYCLE, len(lines)
    return lines


def _lines(n: int, frames: list[dict]) -> Iterator[bytes]:
    """``n`` lines of the cycle, the frames among them stamped with increasing times."""
    cycle = _cycle(frames)
    for i in range(n):
        t = round(i * STEP_S, 6)
        kind, payload = cycle[i % CYCLE]
        if kind == "frame":
            yield json.dumps({**payload, "time_s": t}).encode()  # type: ignore[dict-item]
        elif kind == "full":
            yield json.dumps({**frames[(i // CYCLE) % len(frames)], "time_s": t}).encode()
        elif kind == "strangers":
            objects = [{"label": f"label-{i}-{k}", "x": 50.0 + 100 * k, "y": 60.0} for k in range(3)]
            yield json.dumps({**cycle[1][1], "time_s": t, "objects": objects}).encode()  # type: ignore[dict-item]
        else:
            yield payload  # type: ignore[misc]


def run_navigate(map_path: Path, n: int, frames: list[dict], particles: int) -> dict:
    """Feed ``n`` generated lines to ``mapdb navigate MAP -``, count the records as they stream, sample RSS."""
    try:
        import psutil
    except ImportError:  # the peak from wait4 is still exact; only the samples need psutil
        psutil = None
    start_xy = frames[0]["truth"]
    args = [sys.executable, "-m", "mapdb_cli", "navigate", str(map_path), "-", "--particles", str(particles),
            "--initial", f"{start_xy['x']},{start_xy['y']},30"]
    begin = time.perf_counter()
    proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    non_blank = [0]
    failed: list[BaseException] = []

    def feed() -> None:
        assert proc.stdin is not None
        try:
            with proc.stdin:
                for line in _lines(n, frames):
                    non_blank[0] += bool(line.strip())
                    proc.stdin.write(line + b"\n")
        except BaseException as exc:  # reported by the main thread: a stream cut short measures nothing
            failed.append(exc)

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    child = psutil.Process(proc.pid) if psutil else None
    expected = n - n // CYCLE  # one blank line per cycle
    marks = {max(1, round(expected * q)): q for q in (0.1, 0.5, 0.9)}
    samples: dict[float, int] = {}
    records = placed = 0
    assert proc.stdout is not None and proc.stderr is not None
    for line in proc.stdout:
        records += 1
        placed += b',"x":null,' not in line[:400]
        if child is not None and records in marks:
            samples[marks[records]] = child.memory_info().rss
        if child is not None and records % max(1, expected // 20) == 0:  # progress, for a run cut short
            print(f"  {records:,} records, RSS {child.memory_info().rss / 1e6:.0f} MB, "
                  f"{time.perf_counter() - begin:.0f} s", file=sys.stderr, flush=True)
    writer.join()
    if failed:
        raise RuntimeError(f"writing the stream failed: {failed[0]!r}")
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    if code != 0 or b"Traceback" in err:
        raise RuntimeError(f"mapdb navigate failed ({code}): {err.decode(errors='replace').strip()[-2000:]}")
    return {"non_blank": non_blank[0], "records": records, "placed": placed, "peak": usage.ru_maxrss * 1024,
            "samples": samples, "wall": time.perf_counter() - begin, "cpu": usage.ru_utime + usage.ru_stime}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lines", default="10000,1000000", help="comma-separated stream lengths")
    parser.add_argument("--particles", type=int, default=2000, help="particles of the filter (navigate's default)")
    parser.add_argument("--dir", type=Path, default=None, help="where to build the map (default a temp dir)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        map_path, flight = root / "helsinki.mapdb", root / "flight.jsonl"
        _mapdb("build", str(REPO / "sample_maps" / "helsinki.osm.pbf"), "-o", str(map_path), "-q")
        _mapdb("simulate", "flight", str(map_path), "--length", "400", "--imu-std", "0.3", "-o", str(flight), "-q")
        frames = [json.loads(line) for line in flight.read_text().splitlines()]
        rows = [("(empty stream: the floor)", 0, run_navigate(map_path, 0, frames, args.particles))]
        for n in (int(v) for v in args.lines.split(",")):
            rows.append((f"{n:,} lines", n, run_navigate(map_path, n, frames, args.particles)))
    header = (f"{'stream':28s} {'non-blank':>9s} {'records':>9s} {'placed':>9s} {'peak RSS':>9s} {'RSS@10%':>8s} "
              f"{'RSS@50%':>8s} {'RSS@90%':>8s} {'wall s':>8s} {'cpu s':>8s} {'lines/s':>8s}")
    print(f"mapdb navigate MAP - --particles {args.particles}")
    print(header)
    print("-" * len(header))
    for name, n, r in rows:
        s = r["samples"]
        rss = [f"{s[q] / 1e6:6.0f}MB" if q in s else f"{'':8s}" for q in (0.1, 0.5, 0.9)]
        rate = f"{n / r['wall']:8.0f}" if n else f"{'':8s}"
        print(f"{name:28s} {r['non_blank']:9,d} {r['records']:9,d} {r['placed']:9,d} {r['peak'] / 1e6:7.0f}MB "
              f"{rss[0]} {rss[1]} {rss[2]} {r['wall']:8.1f} {r['cpu']:8.1f} {rate}")
    print()
    same = all(r["records"] == r["non_blank"] for _, _, r in rows)
    print("records == non-blank lines in every run" if same else "records != non-blank lines: MISMATCH")


if __name__ == "__main__":
    main()
