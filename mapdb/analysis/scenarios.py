"""Scenarios: several named configurations run over the same cells, read from a TOML file.

Each table under ``scenario`` is one configuration; the keys it leaves out take the command line's
values (the cells, bounding box and seed are always the command line's, so that scenarios compare)::

    [scenario."all labels"]

    [scenario."buildings only"]
    labels = ["building"]

    [scenario."300 m, 60 deg"]
    altitude = 300
    fov = 60

Keys: ``altitude`` (m), ``fov`` (degrees), ``size`` ("640x480"), ``attitude_std`` (degrees),
``pixel_std`` (pixels), ``miss_rate``, ``spurious_rate``, ``label_noise``, ``labels`` (a list, or
"all"), ``samples``, ``prior`` (m, or ``false`` for none).  Any other key, a value of the wrong type or
out of range, or a file without scenarios is an :class:`~mapdb.errors.AnalysisError` naming the file,
the scenario and the key.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from typing import Any

from ..errors import reading
from .grid import AnalysisError
from .measures import SampleConfig

__all__ = ["MAX_SCENARIOS", "read_scenarios"]

MAX_SCENARIOS = 16
# Upper bounds past which a simulation means nothing (as the command line's options have them).
_LIMITS = {"altitude": 1e5, "attitude_std": 90.0, "pixel_std": 1e6, "spurious_rate": 100.0, "prior": 2e7,
           "samples": 10_000}


def _number(where: str, key: str, value: Any, low: float, high: float, *, open_low: bool = False,
            integer: bool = False) -> float:
    ok_type = isinstance(value, int) if integer else isinstance(value, int | float)
    if isinstance(value, bool) or not ok_type or not math.isfinite(value):
        raise AnalysisError(f"{where}: {key} must be {'an integer' if integer else 'a finite number'}, "
                            f"got {value!r}")
    if value < low or value > high or (open_low and value == low):
        bound = f"above {low:g}" if open_low else f"at least {low:g}"
        raise AnalysisError(f"{where}: {key} must be {bound} and at most {high:g}, got {value!r}")
    return int(value) if integer else float(value)


def _size(where: str, value: Any) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in str(value).lower().split("x"))
    except ValueError:
        raise AnalysisError(f"{where}: size must be WIDTHxHEIGHT (e.g. \"640x480\"), got {value!r}") from None
    if not (isinstance(value, str) and 0 < w <= 100_000 and 0 < h <= 100_000):
        raise AnalysisError(f"{where}: size must be WIDTHxHEIGHT with positive sides, got {value!r}")
    return (w, h)


def _labels(where: str, value: Any) -> tuple[str, ...] | None:
    if value == "all":
        return None
    if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
        raise AnalysisError(f"{where}: labels must be a list of label names or \"all\", got {value!r}")
    return tuple(dict.fromkeys(value))


def _prior(where: str, value: Any) -> float | None:
    if value is False:
        return None
    return _number(where, "prior", value, 0.0, _LIMITS["prior"], open_low=True)


# key -> (SampleConfig field, reader of the value)
_KEYS: dict[str, tuple[str, Any]] = {
    "altitude": ("altitude", lambda w, v: _number(w, "altitude", v, 0.0, _LIMITS["altitude"], open_low=True)),
    "fov": ("fov_deg", lambda w, v: _number(w, "fov", v, 0.0, 179.0, open_low=True)),
    "size": ("size", _size),
    "attitude_std": ("attitude_std", lambda w, v: _number(w, "attitude_std", v, 0.0, _LIMITS["attitude_std"])),
    "pixel_std": ("pixel_std", lambda w, v: _number(w, "pixel_std", v, 0.0, _LIMITS["pixel_std"])),
    "miss_rate": ("miss_rate", lambda w, v: _number(w, "miss_rate", v, 0.0, 1.0)),
    "spurious_rate": ("spurious_rate", lambda w, v: _number(w, "spurious_rate", v, 0.0, _LIMITS["spurious_rate"])),
    "label_noise": ("label_noise", lambda w, v: _number(w, "label_noise", v, 0.0, 1.0)),
    "labels": ("labels", _labels),
    "samples": ("samples", lambda w, v: _number(w, "samples", v, 1, _LIMITS["samples"], integer=True)),
    "prior": ("prior", _prior),
}


def _scenario(where: str, table: Any, base: SampleConfig) -> SampleConfig:
    if not isinstance(table, dict):
        raise AnalysisError(f"{where}: a scenario is a table of settings, got {table!r}")
    unknown = sorted(set(table) - set(_KEYS))
    if unknown:
        raise AnalysisError(f"{where}: unknown key {unknown[0]!r}; a scenario may set "
                            f"{', '.join(_KEYS)}")
    changes = {}
    for key, value in table.items():
        name, read = _KEYS[key]
        changes[name] = read(where, value)
    return dataclasses.replace(base, **changes)


def read_scenarios(path: str | os.PathLike[str], base: SampleConfig) -> dict[str, SampleConfig]:
    """The scenarios of a TOML file, in file order, each ``base`` with the file's settings.

    Examples
    --------
    >>> import tempfile, os
    >>> f = os.path.join(tempfile.mkdtemp(), "s.toml")
    >>> _ = open(f, "w").write('[scenario.low]\\naltitude = 80\\n[scenario.high]\\naltitude = 300\\n')
    >>> {name: c.altitude for name, c in read_scenarios(f, SampleConfig()).items()}
    {'low': 80.0, 'high': 300.0}
    >>> _ = open(f, "w").write('[scenario.low]\\naltitud = 80\\n')
    >>> read_scenarios(f, SampleConfig())  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    mapdb.errors.AnalysisError: ...s.toml: scenario 'low': unknown key 'altitud'; a scenario may set ...
    """
    with reading(os.fspath(path), "scenarios file"), open(path, "rb") as f:
        try:
            doc = tomllib.load(f)
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise AnalysisError(f"{path}: not a valid TOML file ({exc})") from None
    unknown = sorted(set(doc) - {"scenario"})
    if unknown:
        raise AnalysisError(f"{path}: unknown key {unknown[0]!r}; the file holds [scenario.NAME] tables only")
    tables = doc.get("scenario")
    if not isinstance(tables, dict) or not tables:
        raise AnalysisError(f"{path}: no scenarios; give one [scenario.NAME] table per configuration")
    if len(tables) > MAX_SCENARIOS:
        raise AnalysisError(f"{path}: {len(tables)} scenarios, more than {MAX_SCENARIOS}")
    configs = {}
    for name, table in tables.items():
        if not name.strip() or len(name) > 80:
            raise AnalysisError(f"{path}: scenario name {name!r} must be 1 to 80 characters, not blank")
        configs[name] = _scenario(f"{path}: scenario {name!r}", table, base)
    return configs
