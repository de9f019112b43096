"""Label masks written as real PNG or GeoTIFF files, for the tests of ``mapdb objects``."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.errors import NotGeoreferencedWarning


def write_mask(path: Path, array: np.ndarray, transform: Any = None, crs: str | None = None, **profile: Any) -> Path:
    """``array`` as one band of ``path`` (PNG by its suffix, else GeoTIFF), georeferenced when given a transform."""
    driver = "PNG" if path.suffix == ".png" else "GTiff"
    extra = {"transform": transform, "crs": crs} if transform is not None else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver=driver, width=array.shape[1], height=array.shape[0], count=1,
                           dtype=array.dtype, **extra, **profile) as ds:
            ds.write(array, 1)
    return path
