"""The child processes of ``benchmarks/lost_in_space_index.py``: builds, fresh first answers, QuadIndex.

Each runs a piece of code in a fresh Python (:func:`_child`) that prints one JSON line last; its wall time and the
peak memory of it and its workers (sampled every 0.2 s) are added to the result.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path


def _tree_memory(pid: int) -> tuple[int, int]:
    """Resident and proportional (PSS) bytes of a process and all its descendants.

    The resident sets count pages the worker processes share with their parent (forked, copy-on-write)
    once per process: an upper bound.  PSS divides each shared page among its sharers: the real use.
    """
    import psutil

    try:
        p = psutil.Process(pid)
        procs = [p, *p.children(recursive=True)]
    except psutil.Error:
        return 0, 0
    rss = pss = 0
    for q in procs:
        try:
            info = q.memory_full_info()
            rss, pss = rss + info.rss, pss + info.pss
        except psutil.Error:
            pass
    return rss, pss


def _child(code: str, *args: str) -> dict:
    """Run ``code`` in a fresh Python (it prints one JSON line last); its result, wall time and peak memory."""
    peak = [0, 0]
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            rss, pss = _tree_memory(proc.pid)
            peak[0], peak[1] = max(peak[0], rss), max(peak[1], pss)
            time.sleep(0.2)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    out, _ = proc.communicate()
    done.set()
    watcher.join()
    wall = time.perf_counter() - start
    if proc.returncode:
        raise RuntimeError(f"child failed ({proc.returncode}): {code[:80]}...")
    result = json.loads(out.strip().splitlines()[-1])
    result.update(wall_s=wall, peak_rss_mb=peak[0] / 2**20, peak_pss_mb=peak[1] / 2**20,
                  maxrss_children_mb=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
    return result


BUILD = """
import json, sys
from pathlib import Path
sys.path.insert(0, "benchmarks")
if len(sys.argv) > 3:  # a baseline revision's build_index, imported as mapdb_baseline
    from _baseline import import_baseline
    build_index = import_baseline(sys.argv[3], Path(sys.argv[4]), "match.index.stored").build_index
else:
    from mapdb.match.index.stored import build_index
print(json.dumps(build_index(sys.argv[1], workers=int(sys.argv[2]))))
"""

# Drops the map and its index from the page cache, in the child processes below.
DROP_CACHE = """
for path in (sys.argv[1], index_path(sys.argv[1])):
    fd = os.open(path, os.O_RDONLY)
    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    os.close(fd)
"""

OPEN = """
import time
t0 = time.perf_counter()
import json, os, sys
sys.path.insert(0, "benchmarks")
import numpy as np
from lost_in_space_index import _image_arrays, image_queries
from mapdb.match.index.stored import StoredQuadIndex, index_path
from mapdb.mapfile.reader import open_map
image = json.loads(sys.argv[2])
""" + DROP_CACHE + """t1 = time.perf_counter()
m = open_map(sys.argv[1])
ix = StoredQuadIndex.for_map(m)
t2 = time.perf_counter()
z, label, truth = _image_arrays(image, tuple(m.labels))
inv, lab, radius, ids = image_queries(z, label)
row, hit = ix.lookup(inv, lab, radius, 16)
map_z = ix.coordinates(hit)
t3 = time.perf_counter()
print(json.dumps({"imports_s": t1 - t0, "open_s": t2 - t1, "lookup_s": t3 - t2, "open_to_answer_s": t3 - t1,
                  "start_to_answer_s": t3 - t0, "hits": int(len(row))}))
"""

FIRST_ANSWER = """
import time
t0 = time.perf_counter()
import importlib, json, os, sys
from pathlib import Path
sys.path.insert(0, "benchmarks")
package = "mapdb"
if sys.argv[3]:  # a baseline revision, imported as mapdb_baseline
    from _baseline import import_baseline
    import_baseline(sys.argv[3], Path(sys.argv[4]))
    package = "mapdb_baseline"
Localizer = importlib.import_module(package + ".localize").Localizer
index_path = importlib.import_module(package + ".match.index.layout").index_path
open_map = importlib.import_module(package + ".store").open_map
image = json.loads(sys.argv[2])
""" + DROP_CACHE + """t1 = time.perf_counter()
c1 = time.process_time()
m = open_map(sys.argv[1])
answer = Localizer(m).localize(image)
t2 = time.perf_counter()
status = answer.status if hasattr(answer, "status") else answer["status"]
print(json.dumps({"open_to_answer_s": t2 - t1, "start_to_answer_s": t2 - t0,
                  "open_to_answer_cpu_s": time.process_time() - c1, "status": status}))
"""

QUADINDEX = """
import json, sys
sys.path.insert(0, "benchmarks")
from pathlib import Path
from lost_in_space_index import _quadindex_lookups
images = json.loads(Path(sys.argv[2]).read_text())
r = _quadindex_lookups(Path(sys.argv[1]), images)
print(json.dumps(r))
"""
