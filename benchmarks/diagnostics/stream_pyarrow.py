"""Peak memory of reading a GeoParquet layer's ``label, geometry`` with pyarrow, three ways.

Reproduces the README's "pyarrow's ``ParquetFile.iter_batches`` over all row groups grows with what it has
read (iterating ``label, geometry`` only: 405 MB at 5M rows against 174 MB at 1M; one iterator a row group:
120 MB for both)" (the streaming build's section), the cause of the fix "GeoParquet read with one pyarrow
iterator a row group".  ``MODE`` is ``iter`` (one ``iter_batches`` over the whole file, 65,536 rows a
batch), ``itergroup`` (one ``iter_batches`` a row group) or ``readgroup`` (``read_row_group`` each in turn).

The layers are ``benchmarks/layer_memory.py``'s ``world-N.parquet`` (a synthetic world of at least N objects
from the shared extracts, squares for objects with an area, row groups of 65,536).  Run from the repository
root, one mode a process (the peak is the process's)::

    python benchmarks/diagnostics/stream_pyarrow.py --write 1000000 DIR    # writes DIR/world-1000000.parquet
    python benchmarks/diagnostics/stream_pyarrow.py DIR/world-1000000.parquet iter
    python benchmarks/diagnostics/stream_pyarrow.py DIR/world-1000000.parquet itergroup

Prints the mode, the rows read and the process's peak resident set (``getrusage``).
"""

from __future__ import annotations

import argparse
import resource
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
COLUMNS = ["label", "geometry"]


def read(path: Path, mode: str) -> int:
    """Rows of ``label, geometry`` read from ``path`` the ``mode`` way."""
    import pyarrow.parquet as pq

    f = pq.ParquetFile(path)
    n = 0
    if mode == "iter":
        for batch in f.iter_batches(batch_size=65536, columns=COLUMNS, use_threads=False):
            n += batch.num_rows
    elif mode == "itergroup":
        for g in range(f.metadata.num_row_groups):
            for batch in f.iter_batches(batch_size=65536, row_groups=[g], columns=COLUMNS, use_threads=False):
                n += batch.num_rows
    else:
        for g in range(f.metadata.num_row_groups):
            n += f.read_row_group(g, columns=COLUMNS, use_threads=False).num_rows
    return n


def main(argv: list[str] | None = None) -> int:
    """Read the layer (or, with ``--write N DIR``, write one), print the peak."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("file", nargs="?", type=Path, help="a GeoParquet layer")
    parser.add_argument("mode", nargs="?", choices=("iter", "itergroup", "readgroup"))
    parser.add_argument("--write", nargs=2, metavar=("N", "DIR"), help="write world-N.parquet (and .csv) into DIR")
    args = parser.parse_args(argv)
    if args.write:
        from layer_memory import write_layers

        where = Path(args.write[1])
        where.mkdir(parents=True, exist_ok=True)
        _, parquet, count = write_layers(int(args.write[0]), where)
        print(f"{parquet}: {count:,} objects")
        return 0
    if args.file is None or args.mode is None:
        parser.error("FILE and MODE are required (or --write N DIR)")
    if not args.file.is_file():
        print(f"stream_pyarrow: error: {args.file}: no such file", file=sys.stderr)
        return 1
    rows = read(args.file, args.mode)
    print(f"{args.mode} {rows:,} rows, peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
