"""The analysis's cheaper bookkeeping and picture give the same numbers and bytes as the plain ways they replace."""

from __future__ import annotations

import statistics
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import pytest
from towns import write_town

from mapdb.analysis import SampleConfig, pictures
from mapdb.analysis.measures import column_medians
from mapdb.analysis.run import analyze, analyze_scenarios


def test_column_medians_are_numpys() -> None:
    """Random counts (ties, duplicates, one row, odd and even numbers of images) against ``np.median``."""
    rng = np.random.default_rng(7)
    cases = [np.zeros((1, 1), np.int64), np.array([[5, 0, 2]]), np.full((16, 3), 4), np.array([[0], [2**40]])]
    cases += [rng.integers(0, int(top), (int(n), int(k))) for top, n, k in
              zip(rng.choice([2, 6, 50, 10**6], 300), rng.integers(1, 33, 300), rng.integers(1, 7, 300), strict=True)]
    for values in cases:
        got = column_medians(values)
        assert got.dtype == np.float64 and np.array_equal(got, np.median(values, axis=0)), values


def test_statistics_median_is_numpys_for_the_cells_floats() -> None:
    """A cell's error and ambiguity medians (finite floats, NaN already left out): the same doubles."""
    rng = np.random.default_rng(8)
    for n in list(range(1, 20)) * 20:
        values = [float(v) for v in rng.random(n) * 10.0 ** float(rng.integers(-4, 3))]
        if n % 3 == 0:
            values = [round(v, 2) for v in values] + values[:2]  # ties
        assert statistics.median(values) == float(np.median(values))
    assert statistics.median([0.0, 1.0]) == 0.5 and statistics.median([0.3]) == 0.3


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Path:
    return write_town(tmp_path_factory.mktemp("cheaper") / "town.mapdb", 400, 4, 400.0, 300.0)


def _small_figure(path: Path, once: bool) -> bytes:
    """Two panels as the analysis draws them (an image, a colour bar, titles, a suptitle), laid out by
    ``tight_layout(rect=...)`` with or without each axes measured once; the PNG's bytes."""
    plt = pictures.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(6, 3))
    for k, ax in enumerate(axes):
        image = ax.imshow(np.arange(12.0).reshape(3, 4) * (k + 1), extent=(0, 4000, 0, 3000))
        plt.colorbar(image, ax=ax, shrink=0.85, pad=0.02).set_label("a measure (%)", fontsize=8)
        ax.set_title(f"panel {k}: a long title of what it adds up to", fontsize=9, loc="left")
        ax.set_ylabel("northing (km)")
    fig.suptitle("Where a map localizes an aircraft\nsecond line", fontsize=11)
    with pictures._measured_once(fig) if once else nullcontext():
        fig.tight_layout(rect=(0, 0.02, 1, 0.96))
    pictures._laid_out(fig)
    pictures.save_figure(fig, path, 60)
    return path.read_bytes()


def test_tight_layout_measured_once_gives_the_same_bytes(tmp_path: Path) -> None:
    assert _small_figure(tmp_path / "once.png", True) == _small_figure(tmp_path / "plain.png", False)


@pytest.mark.slow
def test_picture_is_the_same_bytes_when_each_axes_is_measured_once(town: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The analysis's picture with each axes's box measured once, and as often as matplotlib asks: the same PNG."""
    one = analyze(str(town), SampleConfig(samples=2))
    pictures.plot_analysis(tmp_path / "once.png", one)
    monkeypatch.setattr(pictures, "_measured_once", lambda fig: nullcontext())
    pictures.plot_analysis(tmp_path / "plain.png", one)
    assert (tmp_path / "once.png").read_bytes() == (tmp_path / "plain.png").read_bytes()


@pytest.mark.slow
def test_scenarios_picture_is_the_same_bytes_when_each_axes_is_measured_once(
        town: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    both = analyze_scenarios(str(town), {"a": SampleConfig(samples=2), "b": SampleConfig(samples=2, altitude=120)})
    pictures.plot_scenarios(tmp_path / "once.png", both)
    monkeypatch.setattr(pictures, "_measured_once", lambda fig: nullcontext())
    pictures.plot_scenarios(tmp_path / "plain.png", both)
    assert (tmp_path / "once.png").read_bytes() == (tmp_path / "plain.png").read_bytes()


def test_measured_once_leaves_the_axes_as_they_were(town: Path) -> None:
    """The kept measures are an attribute of each axes only within the block."""
    plt = pictures.pyplot()
    fig, axes = plt.subplots(1, 2)
    try:
        with pictures._measured_once(fig):
            assert all("get_tightbbox" in vars(ax) for ax in axes)
            fig.tight_layout(rect=(0, 0.02, 1, 0.96))
        assert not any("get_tightbbox" in vars(ax) for ax in axes)
    finally:
        plt.close(fig)
