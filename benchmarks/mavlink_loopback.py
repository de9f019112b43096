"""A navigated flight sent over ``mapdb navigate --mavlink`` to a pymavlink listener on loopback (issue 32).

Builds the sample map, simulates a flight over it (``mapdb simulate flight``, ``--length`` metres), navigates
it with ``--mavlink udpout:127.0.0.1:PORT --mavlink-vision`` to a UDP socket of this script, decodes every
datagram with pymavlink and compares each ``GPS_INPUT`` with its track record; then navigates again with
nobody listening.

Run from the repository root (needs ``pip install 'mapdb[mavlink]'``)::

    python benchmarks/mavlink_loopback.py [--length 500]

Prints: records, messages decoded by type, the largest difference between a message's lat/lon and the
record's (degrees), the largest between ``horiz_accuracy`` and the covariance's major-axis sigma, and the
losses counted with and without a receiver.
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SAMPLE = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"


def mapdb(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapdb_cli", *args], capture_output=True, text=True, check=True)


def received(sock: socket.socket) -> list:
    from pymavlink.dialects.v20 import common

    parser, messages = common.MAVLink(None), []
    sock.settimeout(1.0)
    try:
        while True:
            messages += parser.parse_buffer(sock.recv(65536)) or []
    except TimeoutError:
        return messages


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--length", type=float, default=500.0, help="Metres flown (20 m/s, 10 frames a second).")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        mapdb("build", str(SAMPLE), "-o", str(root / "m.mapdb"), "-q")
        mapdb("simulate", "flight", str(root / "m.mapdb"), "-o", str(root / "f.jsonl"), "--length", str(args.length),
              "--pixel-std", "1", "--attitude-std", "0.1", "--seed", "1", "-q")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        done = mapdb("navigate", str(root / "m.mapdb"), str(root / "f.jsonl"), "-o", str(root / "t.jsonl"),
                     "--mavlink", f"udpout:127.0.0.1:{port}", "--mavlink-vision")
        messages = received(sock)
        sock.close()
        records = [json.loads(line) for line in (root / "t.jsonl").read_text().splitlines()]
        gone = mapdb("navigate", str(root / "m.mapdb"), str(root / "f.jsonl"), "-o", str(root / "t2.jsonl"),
                     "--mavlink", f"udpout:127.0.0.1:{port}", "-q")
    gps = [m for m in messages if m.get_type() == "GPS_INPUT"]
    placed = [(r, m) for r, m in zip(records, gps) if r["lat"] is not None]
    dpos = max(max(abs(m.lat / 1e7 - r["lat"]), abs(m.lon / 1e7 - r["lon"])) for r, m in placed)
    dacc = max(abs(m.horiz_accuracy - math.sqrt(np.linalg.eigvalsh(np.array(r["cov_m2"]))[-1])) for r, m in placed)
    kinds = {k: sum(m.get_type() == k for m in messages) for k in sorted({m.get_type() for m in messages})}
    print("| measure | value |\n|---|---|")
    print(f"| track records | {len(records)} |")
    for kind, n in kinds.items():
        print(f"| {kind} decoded | {n} |")
    print(f"| largest lat/lon difference, message vs record | {dpos:.2e} deg |")
    print(f"| largest horiz_accuracy vs covariance sigma (record's cov_m2 has 4 decimals) | {dacc:.2e} m |")
    print(f"| with a receiver: stderr | {done.stderr.strip().splitlines()[-1]} |")
    print(f"| nobody listening: stderr | {gone.stderr.strip().splitlines()[-1]} |")


if __name__ == "__main__":
    main()
