"""The frame-to-frame velocity's bias on the rendered-mask flights, split by cause (issue 29, velocity bias).

Navigates a cached flight of ``benchmarks/navigation_masks.py`` (the frames carry their truth) and, for every
frame whose velocity the navigator measured after its first fix, splits the measured velocity's error
against the truth into:

* **corrected** / **measured**: the velocity's error with the bias ``--mode`` takes out (the navigator's
  velocity) and before it;
* **scale / heading**: ``(A_nav - A_true) b / dt``, the carried similarity's error (``A_nav`` the last fix's
  scale and heading carried by the barometer and the yaw; ``A_true`` the true height over the focal length
  and the true heading);
* **motion**: ``A_true b / dt - v_true``, the fitted image motion's own error (relief, blob shapes, which
  blobs, levelling);

and refits the motion's translation (its ``a`` kept) on the whole pairs of one label class only
(**buildings** / **ground**: roads, parks, water... with no relief), each turned into m/s with the true
similarity.  Prints, per flight, each part's mean along and across the true track (m/s) with its standard
error, and the mean relative scale error of the carried similarity.

Run from the repository root (the cache of ``navigation_masks.py``; flights missing from it are rendered)::

    python benchmarks/diagnostics/velocity_bias.py --maps andorra,monaco --cases heights,thin15 \
        --cache /tmp/pose-cache
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import navigation_masks as nm  # noqa: E402

from mapdb.camera import Camera  # noqa: E402
from mapdb.match.geometry import image_to_map  # noqa: E402
from mapdb.navigation import navigator as nav_module  # noqa: E402

PAIR_PX = 6.0


def _pairs(prev: Any, cur: Any, motion: Any) -> tuple[np.ndarray, np.ndarray]:
    """Indices (cur, prev) of the whole objects the motion pairs (nearest of one label within PAIR_PX)."""
    d = np.abs(prev.z[None, :] - (motion.a * cur.z + motion.b)[:, None])
    d[cur.codes[:, None] != prev.codes[None, :]] = np.inf
    if cur.border is not None:
        d[cur.border, :] = np.inf
    if prev.border is not None:
        d[:, prev.border] = np.inf
    j = np.argmin(d, axis=1)
    k = np.flatnonzero(d[np.arange(cur.z.size), j] <= PAIR_PX)
    return k, j[k]


def _subset_b(prev: Any, cur: Any, motion: Any, keep: np.ndarray) -> complex | None:
    """The translation (``a`` kept) of the whole pairs whose label code is in ``keep``; None without one."""
    k, j = _pairs(prev, cur, motion)
    mask = np.isin(cur.codes[k], keep)
    if not mask.any():
        return None
    return complex(np.mean(prev.z[j[mask]] - motion.a * cur.z[k[mask]]))


def _stats(values: list[complex]) -> str:
    if len(values) < 2:
        return "n/a"
    e = np.array(values)
    root = math.sqrt(e.size)
    return (f"{e.real.mean():+.3f}±{e.real.std(ddof=1) / root:.3f} / {e.imag.mean():+.3f}±"
            f"{e.imag.std(ddof=1) / root:.3f}")


def diagnose(frames: list[dict[str, Any]], map_path: Path, mode: str) -> dict[str, Any]:
    """Navigate the frames (``velocity_bias=mode``), returning the error parts (complex, along + i across the
    true track) per frame."""
    from mapdb.mapfile.reader import open_map

    captured: dict[str, Any] = {}
    match, to_velocity = nav_module.match_frames, nav_module.velocity_from_motion

    def match_spy(prev: Any, cur: Any, *args: Any, **kw: Any) -> Any:
        captured["pair"] = (prev, cur)
        return match(prev, cur, *args, **kw)

    def velocity_spy(motion: Any, prev_to_map: complex, dt: float, **kw: Any) -> Any:
        captured["motion"] = (motion, prev_to_map, dt)
        captured["applied"] = navigator.bias.applied
        return to_velocity(motion, prev_to_map, dt, **kw)

    names = ("corrected", "total", "scale_heading", "motion", "buildings", "ground")
    parts: dict[str, list[complex]] = {k: [] for k in names}
    scale_err: list[float] = []
    nav_module.match_frames, nav_module.velocity_from_motion = match_spy, velocity_spy
    try:
        with open_map(map_path) as m:
            navigator = nav_module.Navigator(m, options=nav_module.NavigatorOptions(velocity_bias=mode))
            building = [c for name, c in navigator.labels.items() if name == "building"]
            fixed, prev_truth = False, None
            for i, frame in enumerate(frames):
                captured.clear()
                record = navigator.step(frame, f"frame {i}")
                fixed = fixed or record.status == "fix"
                truth = frame["truth"]
                v_true = complex(*truth["velocity_mps"])
                if fixed and "motion" in captured and prev_truth is not None and abs(v_true) > 0:
                    _add(parts, scale_err, captured, frame, prev_truth, v_true, building)
                prev_truth = truth
    finally:
        nav_module.match_frames, nav_module.velocity_from_motion = match, to_velocity
    return {"parts": parts, "scale_err": scale_err}


def _add(parts: dict[str, list[complex]], scale_err: list[float], captured: dict[str, Any], frame: dict[str, Any],
         prev_truth: dict[str, Any], v_true: complex, building: list[int]) -> None:
    """One frame's error parts (module docs), rotated into the true track's frame."""
    motion, a_nav, dt = captured["motion"]
    prev, cur = captured["pair"]
    focal = Camera(frame["width"], frame["height"], frame["camera"]["fov_deg"]).focal_px
    a_true = image_to_map(prev_truth["altitude_m"] / focal, prev_truth["heading_deg"])
    rot = (v_true / abs(v_true)).conjugate()
    parts["total"].append((a_nav * motion.b / dt - v_true) * rot)
    parts["corrected"].append((a_nav * motion.b / dt * (1.0 + captured["applied"]) - v_true) * rot)
    parts["scale_heading"].append((a_nav - a_true) * motion.b / dt * rot)
    parts["motion"].append((a_true * motion.b / dt - v_true) * rot)
    scale_err.append(abs(a_nav) / abs(a_true) - 1.0)
    codes = np.union1d(prev.codes, cur.codes)
    for name, keep in (("buildings", np.array(building)), ("ground", np.setdiff1d(codes, building))):
        b = _subset_b(prev, cur, motion, keep)
        if b is not None:
            parts[name].append((a_true * b / dt - v_true) * rot)


def main() -> None:
    """Parse the options, diagnose each flight, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", default="andorra,monaco")
    parser.add_argument("--cases", default="heights,thin15")
    parser.add_argument("--altitude", type=float, default=120.0)
    parser.add_argument("--length", type=float, default=3000.0)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/pose-cache"))
    parser.add_argument("--mode", default="scale", help="the navigator's velocity_bias (%(default)s)")
    args = parser.parse_args()
    print("| flight | frames | corrected | measured | scale/heading | motion (true A) | buildings only | ground only "
          "| scale rel. error |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.maps.split(","):
        for case in args.cases.split(","):
            frames = nm._flight(name, case, args.altitude, args.length, args.cache)
            full, thin = nm._maps(name, args.cache)
            out = diagnose(frames, thin if case == "thin15" else full, args.mode)
            p = out["parts"]
            print(f"| {name} {case} | {len(p['total'])} | {_stats(p['corrected'])} | {_stats(p['total'])} "
                  f"| {_stats(p['scale_heading'])} "
                  f"| {_stats(p['motion'])} | {_stats(p['buildings'])} ({len(p['buildings'])}) "
                  f"| {_stats(p['ground'])} ({len(p['ground'])}) | {np.mean(out['scale_err']):+.4f} |", flush=True)


if __name__ == "__main__":
    main()
