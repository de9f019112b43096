"""Commands interrupted at random moments by SIGINT or SIGTERM: exit status, time to exit, what is left behind.

Each command first runs once uninterrupted (its duration T); then ``--runs`` times it is sent SIGINT or SIGTERM
(alternately) at a moment drawn uniformly between 0.2 s and 0.9 T, to the process (as ``kill`` does) or, rows
ending "group", to its whole process group (as Ctrl-C in a terminal does: the workers get it too).  Every run
writes over an earlier output with ``--overwrite``.  Per command the table gives: runs the signal reached
mid-run, their exit statuses (130 = SIGINT, 143 = SIGTERM; 0 when the command finished first), the longest
time from the signal to exit, runs whose stderr did not end with the one "interrupted" line or held a
traceback, runs that left a hidden temporary file or folder, and runs whose output was neither the earlier one
intact nor the new one complete (a partial output).  A negative status is a death by that signal: it comes
after the command, once Python has restored the default handlers while shutting down.

Usage: ``python benchmarks/interrupts.py [--runs 10] [--workdir DIR]``.  Uses the Andorra extract of
``../shared/data`` when present, else the Helsinki sample.  The machine is shared: times to exit include waits
for a busy CPU.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared" / "data", ROOT.parents[1] / "shared" / "data",
                           Path("/work/shared/data")) if p.exists()), None)
ANDORRA = None if SHARED is None else SHARED / "osm" / "andorra-2021-06-22.osm.pbf"
SAMPLE = ROOT / "sample_maps" / "helsinki.osm.pbf"


def mapdb(*args: object) -> list[str]:
    return [sys.executable, "-m", "mapdb_cli", *map(str, args)]


def snapshot(path: Path) -> str | None:
    """SHA-256 of a file, or of a folder's file names and contents; None when there is nothing."""
    if path.is_dir():
        h = hashlib.sha256()
        for child in sorted(path.iterdir()):
            h.update(child.name.encode() + hashlib.sha256(child.read_bytes()).digest())
        return h.hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else None


def hidden(work: Path) -> list[str]:
    return sorted(p.name for p in work.iterdir() if p.name.startswith("."))


def complete(out: Path, earlier: str | None) -> bool:
    """A finished run's output: a new file, or a folder with its summary."""
    return (out / "summary.json").exists() if out.is_dir() else snapshot(out) not in (None, earlier)


def one_run(argv: list[str], work: Path, out: Path, delay: float, signum: int, group: bool) -> dict:
    """One run of ``argv`` over an earlier ``out`` (a file written here, or the previous run's folder), sent
    ``signum`` after ``delay`` seconds: to the process, or with ``group`` to its whole process group (workers
    included), as Ctrl-C in a terminal does."""
    if not out.is_dir():
        out.write_bytes(b"the earlier output\n")
    earlier = snapshot(out)
    proc = subprocess.Popen(argv, cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    time.sleep(delay)
    signalled = proc.poll() is None
    sent = time.perf_counter()
    if signalled:
        if group:
            os.killpg(proc.pid, signum)
        else:
            proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=600)
    to_exit = time.perf_counter() - sent
    lines = stderr.decode(errors="replace").splitlines()
    interrupted = proc.returncode in (130, 143)
    clean_message = bool(lines) and lines[-1].startswith("mapdb: interrupted by ") and b"Traceback" not in stderr
    # Never partial: the earlier output as it was, or (the command finished first) the new one complete.
    intact = snapshot(out) == earlier or complete(out, earlier)
    return {"signalled": signalled, "status": proc.returncode, "to_exit": to_exit if signalled else None,
            "bad_stderr": interrupted and not clean_message, "left": hidden(work), "intact": intact,
            "delay": delay, "signal": signal.Signals(signum).name, "stderr": lines[-6:]}


def table(rows: list[tuple[str, list[dict], float]]) -> None:
    print(f"{'command':<34}{'T s':>6}{'mid-run':>8}  {'exit statuses':<22}{'max s to exit':>14}"
          f"{'bad stderr':>11}{'left files':>11}{'output ok':>10}")
    for name, runs, duration in rows:
        mid = [r for r in runs if r["signalled"]]
        statuses: dict[int, int] = {}
        for r in mid:
            statuses[r["status"]] = statuses.get(r["status"], 0) + 1
        shown = ", ".join(f"{s}: {n}" for s, n in sorted(statuses.items()))
        slowest = max((r["to_exit"] for r in mid), default=0.0)
        print(f"{name:<34}{duration:>6.1f}{len(mid):>8}  {shown:<22}{slowest:>14.2f}"
              f"{sum(r['bad_stderr'] for r in runs):>11}{sum(bool(r['left']) for r in runs):>11}"
              f"{sum(r['intact'] for r in runs):>7}/{len(runs)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="interrupts."))
    work.mkdir(parents=True, exist_ok=True)
    source = ANDORRA if ANDORRA is not None and ANDORRA.exists() else SAMPLE
    subprocess.run(mapdb("build", source, "-o", "m.mapdb", "-q", "--overwrite"), cwd=work, check=True,
                   stdout=subprocess.DEVNULL)
    subprocess.run(mapdb("simulate", "m.mapdb", "-o", "images.jsonl", "--n", "300", "--yaw", "random",
                         "--min-objects", "6", "-q", "--overwrite"), cwd=work, check=True)
    print(f"source: {source.name}; work folder {work}; {args.runs} runs a command\n")
    index = mapdb("index", "m.mapdb", "-o", "out.qidx", "--overwrite", "--workers", "2")
    commands = {
        "build": (mapdb("build", source, "-o", "out.mapdb", "--overwrite"), "out.mapdb"),
        "index (2 forked workers)": (index, "out.qidx"),
        "index (2 forked workers), group": (index, "out.qidx"),
        "query (300 images)": (mapdb("query", "m.mapdb", "images.jsonl", "-o", "out.jsonl", "--overwrite"),
                               "out.jsonl"),
        "simulate --n 5000": (mapdb("simulate", "m.mapdb", "-o", "out.jsonl", "--n", "5000", "--overwrite"),
                              "out.jsonl"),
        "analyze --cell 1000 --samples 4": (mapdb("analyze", "m.mapdb", "-o", "outdir", "--cell", "1000",
                                                  "--samples", "4", "--overwrite"), "outdir"),
        "analyze ... --jobs 2 (Dask), group": (mapdb("analyze", "m.mapdb", "-o", "outdir", "--cell", "1000",
                                                     "--samples", "4", "--jobs", "2", "--overwrite"), "outdir"),
    }
    rng = random.Random(args.seed)
    rows = []
    for name, (argv, out) in commands.items():
        start = time.perf_counter()
        subprocess.run(argv, cwd=work, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        duration = time.perf_counter() - start
        runs = [one_run(argv, work, work / out, rng.uniform(0.2, max(0.3, 0.9 * duration)),
                        (signal.SIGINT, signal.SIGTERM)[k % 2], name.endswith(", group")) for k in range(args.runs)]
        rows.append((name, runs, duration))
    table(rows)
    for name, runs, _ in rows:  # what went wrong, to look into
        for r in runs:
            if r["bad_stderr"] or r["left"] or not r["intact"]:
                print(f"\n{name}: {r['signal']} after {r['delay']:.2f} s: exit {r['status']}, left {r['left']}, "
                      f"output ok {r['intact']}; stderr ends:", *r["stderr"], sep="\n  ")


if __name__ == "__main__":
    main()
