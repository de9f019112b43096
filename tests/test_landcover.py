"""Tests of the land-cover raster source on GeoTIFFs written here, and on the real CORINE/WorldCover rasters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import Geod, Transformer
from rasterio import Affine
from scipy import ndimage

from mapdb.errors import MapdbIOError, SourceError
from mapdb.labels import default_label_table, load_label_table
from mapdb.sources.landcover.reader import is_raster_path, raster_class_table_name, read_landcover
from mapdb.sources.suffixes import RASTER_SUFFIXES

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "landcover"
TABLE = default_label_table()
CORINE_FILES = {
    "corine2000_bern_valais_g100_clc00.tif": "EPSG:3035",
    "corine2006_lausanne_ls100_06.tif": "EPSG:2056",
}
WORLDCOVER = "ESA_WorldCover_10m_2021_v200_N00E006_Map.tif"

# CORINE grid codes used below (default table): 41 water bodies -> water, 24 coniferous -> forest,
# 44 sea and ocean -> no label.
WATER, FOREST, SEA = 41, 24, 44

# A 10 m UTM grid; pixel (row, col) has its centre at (X0 + 10 col + 5, Y0 - 10 row - 5).
X0, Y0, PIXEL = 500_000.0, 5_000_000.0, 10.0


def from_origin(west: float, north: float, xres: float, yres: float) -> Affine:
    """North-up grid transform (rasterio's own helper warns about Affine's ``*`` operator)."""
    return Affine(xres, 0.0, west, 0.0, -yres, north)


def write_raster(path: Path, array: np.ndarray, crs: str | None = "EPSG:32632", transform=None,
                 nodata: float | None = None, block_rows: int | None = None) -> Path:
    profile = {
        "driver": "GTiff", "width": array.shape[-1], "height": array.shape[-2],
        "count": 1 if array.ndim == 2 else array.shape[0], "dtype": array.dtype.name,
        "transform": transform if transform is not None else from_origin(X0, Y0, PIXEL, PIXEL),
    }
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    if block_rows is not None:
        profile["blockysize"] = block_rows
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(array if array.ndim == 3 else array[np.newaxis])
    return path


def patch_reference(pixels: np.ndarray) -> tuple[float, float, float]:
    """Centroid x, y and area of a patch on the UTM test grid, from its (row, col) pixel list."""
    rows, cols = pixels[:, 0], pixels[:, 1]
    return X0 + PIXEL * (cols.mean() + 0.5), Y0 - PIXEL * (rows.mean() + 0.5), PIXEL * PIXEL * len(pixels)


def rect(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """(row, col) of every pixel of rows r0..r1-1, cols c0..c1-1."""
    rr, cc = np.mgrid[r0:r1, c0:c1]
    return np.column_stack([rr.ravel(), cc.ravel()])


def paint(array: np.ndarray, pixels: np.ndarray, code: int) -> None:
    array[pixels[:, 0], pixels[:, 1]] = code


def as_set(objects) -> list[tuple[str, float, float, float]]:
    return sorted(zip(objects.names().tolist(), np.round(objects.x, 6).tolist(), np.round(objects.y, 6).tolist(),
                      np.round(objects.area, 6).tolist(), strict=True))


# Known patches on a 24 x 40 grid.  With strips of 8 rows the seams fall between rows 7|8 and 15|16.
LAKE = rect(1, 5, 2, 9)                                   # water, inside the first strip
# water, L-shaped, across the 7|8 seam, with a tail that reaches the next seam too
RIVER = np.concatenate([rect(5, 12, 14, 17), rect(10, 12, 17, 23), rect(12, 18, 21, 23)])
POND = rect(20, 21, 2, 4)                                 # water, 2 pixels = 200 m^2: below the minimum
# Forest blocks touching only corner to corner across the 7|8 seam: one patch (8-connectivity) or two.
WOOD_A = rect(3, 8, 30, 34)
WOOD_B = rect(8, 13, 34, 38)
SEA_PIXELS = rect(19, 23, 30, 38)                         # code with no label


@pytest.fixture()
def patches_tif(tmp_path: Path) -> Path:
    array = np.zeros((24, 40), np.uint8)
    for pixels, code in [(LAKE, WATER), (RIVER, WATER), (POND, WATER), (WOOD_A, FOREST), (WOOD_B, FOREST),
                         (SEA_PIXELS, SEA)]:
        paint(array, pixels, code)
    return write_raster(tmp_path / "clc_patches.tif", array, nodata=255)


def expected(connectivity: int) -> list[tuple[str, float, float, float]]:
    woods = [np.concatenate([WOOD_A, WOOD_B])] if connectivity == 8 else [WOOD_A, WOOD_B]
    rows = [("water", *patch_reference(LAKE)), ("water", *patch_reference(RIVER))]
    rows += [("forest", *patch_reference(w)) for w in woods]
    return sorted((n, round(x, 6), round(y, 6), round(a, 6)) for n, x, y, a in rows)


@pytest.mark.parametrize("tile", [None, (1, 40), (3, 40), (8, 40), (8, 7), (5, 3), (1, 1), (24, 9)])
@pytest.mark.parametrize("connectivity", [8, 4])
def test_patches_centroids_and_areas_exact_across_tile_edges(patches_tif: Path, tile, connectivity) -> None:
    objects = read_landcover(patches_tif, TABLE, min_area_m2=1000.0, connectivity=connectivity, _tile=tile)
    assert objects.crs == "EPSG:32632"
    assert objects.labels == TABLE.labels
    assert as_set(objects) == expected(connectivity)


def test_min_area_keeps_small_patches_when_lowered(patches_tif: Path) -> None:
    objects = read_landcover(patches_tif, TABLE, min_area_m2=0.0, _tile=(8, 40))
    pond = ("water", *(round(v, 6) for v in patch_reference(POND)))
    assert pond in as_set(objects)
    assert objects.counts() == {"water": 3, "forest": 1}


@pytest.mark.parametrize("tile", [(1, 50), (5, 5), (7, 3), (1, 1), (3, 8)])
@pytest.mark.parametrize("direction", [1, -1])
def test_patch_spanning_many_tiles_is_one_object(tmp_path: Path, tile, direction: int) -> None:
    # A diagonal staircase one pixel wide: every pixel meets the next only at a corner, and with square
    # tiles it crosses from tile to tile exactly at tile corners (above-left, or above-right going -1).
    array = np.zeros((50, 50), np.uint8)
    idx = np.arange(50)
    array[idx, idx[::direction]] = FOREST
    path = write_raster(tmp_path / "clc_diagonal.tif", array)
    eight = read_landcover(path, TABLE, min_area_m2=0.0, _tile=tile)
    assert len(eight) == 1 and eight.area[0] == pytest.approx(50 * PIXEL * PIXEL)
    assert eight.x[0] == pytest.approx(X0 + PIXEL * 25) and eight.y[0] == pytest.approx(Y0 - PIXEL * 25)
    four = read_landcover(path, TABLE, min_area_m2=0.0, connectivity=4, _tile=tile)
    assert len(four) == 50


def test_labels_merge_codes_into_one_patch(tmp_path: Path) -> None:
    # CORINE 23 (broad-leaved) and 24 (coniferous) are both "forest": side by side they are one patch.
    array = np.zeros((10, 10), np.uint8)
    array[2:6, 2:5] = 23
    array[2:6, 5:8] = 24
    objects = read_landcover(write_raster(tmp_path / "clc_mixed_forest.tif", array), TABLE, min_area_m2=0.0)
    assert objects.counts() == {"forest": 1}
    assert objects.area[0] == pytest.approx(24 * PIXEL * PIXEL)


def test_nodata_pixels_are_not_objects(tmp_path: Path) -> None:
    # The nodata value is a code the table maps to a label: its pixels must still be ignored.
    array = np.zeros((20, 20), np.uint8)
    array[1:8, 1:8] = WATER
    array[10:18, 10:18] = FOREST
    path = write_raster(tmp_path / "clc_nodata.tif", array, nodata=WATER)
    objects = read_landcover(path, TABLE, min_area_m2=0.0)
    assert objects.counts() == {"forest": 1}


def test_mask_band_pixels_are_not_objects(tmp_path: Path) -> None:
    # No nodata value but an internal mask band (GDAL_TIFF_INTERNAL_MASK) hiding the water block.
    array = np.zeros((20, 20), np.uint8)
    array[1:8, 1:8] = WATER
    array[10:18, 10:18] = FOREST
    path = write_raster(tmp_path / "clc_masked.tif", array)
    valid = np.full(array.shape, 255, np.uint8)
    valid[0:9, 0:9] = 0
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "r+") as dst:
        dst.write_mask(valid)
    assert read_landcover(path, TABLE, min_area_m2=0.0).counts() == {"forest": 1}


def test_geographic_raster_areas_and_centroids(tmp_path: Path) -> None:
    # 0.001 degree pixels at 60 N: about 111 m x 56 m, so pixel area halves from equator to here.
    res = 0.001
    transform = from_origin(10.0, 60.2, res, res)
    array = np.zeros((300, 100), np.uint8)
    array[20:140, 10:40] = WATER       # a tall patch: pixel area changes along it
    array[200:230, 50:90] = FOREST
    path = write_raster(tmp_path / "clc_lonlat.tif", array, crs="EPSG:4326", transform=transform)
    objects = read_landcover(path, TABLE, min_area_m2=0.0, _tile=(64, 100))
    assert objects.crs == "EPSG:4326"
    geod = Geod(ellps="WGS84")
    for name, (r0, r1, c0, c1) in [("water", (20, 140, 10, 40)), ("forest", (200, 230, 50, 90))]:
        (i,) = np.flatnonzero(objects.names() == name)
        west, east = 10.0 + c0 * res, 10.0 + c1 * res
        north, south = 60.2 - r0 * res, 60.2 - r1 * res
        true_area = abs(geod.polygon_area_perimeter([west, east, east, west], [south, south, north, north])[0])
        assert objects.area[i] == pytest.approx(true_area, rel=0.01)
        # The area-weighted centroid is a little south of the middle latitude (southern rows are larger).
        assert objects.x[i] == pytest.approx((west + east) / 2, abs=1e-9)
        assert (south + north) / 2 - 2e-4 < objects.y[i] < (south + north) / 2


def test_bbox_reads_only_the_window_and_filters_by_centroid(tmp_path: Path) -> None:
    array = np.zeros((200, 200), np.uint8)
    array[10:30, 10:30] = WATER        # north-west
    array[150:180, 150:180] = FOREST   # south-east
    path = write_raster(tmp_path / "clc_bbox.tif", array)
    to_lonlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    # A lon/lat box around the south-east patch only (projected corners of rows 140..190, cols 140..190).
    lon0, lat0 = to_lonlat.transform(X0 + 140 * PIXEL, Y0 - 190 * PIXEL)
    lon1, lat1 = to_lonlat.transform(X0 + 190 * PIXEL, Y0 - 140 * PIXEL)
    objects = read_landcover(path, TABLE, min_area_m2=0.0, bbox=(lon0, lat0, lon1, lat1))
    assert objects.counts() == {"forest": 1}
    assert objects.x[0] == pytest.approx(X0 + 165 * PIXEL) and objects.area[0] == pytest.approx(900 * 100.0)
    # A box far away: nothing, and no error.
    assert len(read_landcover(path, TABLE, bbox=(100.0, -10.0, 101.0, -9.0))) == 0


def test_bbox_keeps_only_centroids_inside_the_lonlat_box(tmp_path: Path) -> None:
    # In EPSG:3035 over Finland the grid is turned ~13 degrees from the meridians, so the projected
    # window read for a lon/lat box has corners outside the box: a patch there must be dropped.
    from rasterio.warp import transform_bounds

    bbox = (25.0, 62.0, 25.1, 62.05)
    left, bottom, right, top = transform_bounds("EPSG:4326", "EPSG:3035", *bbox)
    ox, oy = left - 1000.0, top + 1000.0
    width, height = int((right - left + 2000) // 100) + 1, int((top - bottom + 2000) // 100) + 1
    to_lonlat = Transformer.from_crs("EPSG:3035", "EPSG:4326", always_xy=True)

    def pixel_of(x: float, y: float) -> tuple[int, int]:
        return int((oy - y) // 100), int((x - ox) // 100)

    array = np.zeros((height, width), np.uint8)
    mid_r, mid_c = pixel_of((left + right) / 2, (bottom + top) / 2)
    array[mid_r - 2:mid_r + 3, mid_c - 2:mid_c + 3] = WATER
    corner_r, corner_c = pixel_of(left + 150.0, top - 150.0)
    array[corner_r - 1:corner_r + 2, corner_c - 1:corner_c + 2] = FOREST
    lon, lat = to_lonlat.transform(ox + (corner_c + 0.5) * 100, oy - (corner_r + 0.5) * 100)
    assert not (bbox[0] <= lon <= bbox[2] and bbox[1] <= lat <= bbox[3])  # the test's own premise
    path = write_raster(tmp_path / "clc_finland.tif", array, crs="EPSG:3035", transform=from_origin(ox, oy, 100, 100))

    assert read_landcover(path, TABLE, min_area_m2=0.0).counts() == {"water": 1, "forest": 1}
    assert read_landcover(path, TABLE, min_area_m2=0.0, bbox=bbox).counts() == {"water": 1}


def test_bbox_cuts_patches_at_the_window_edge(tmp_path: Path) -> None:
    array = np.zeros((100, 100), np.uint8)
    array[40:60, 10:90] = WATER        # wide patch, centroid at column 50
    path = write_raster(tmp_path / "clc_wide.tif", array)
    to_lonlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    # Box over columns 0..30: the part read (columns 10..30, centroid ~20) is inside the box: kept, cut.
    lon0, lat0 = to_lonlat.transform(X0, Y0 - 100 * PIXEL)
    lon1, lat1 = to_lonlat.transform(X0 + 30 * PIXEL, Y0)
    part = read_landcover(path, TABLE, min_area_m2=0.0, bbox=(lon0, lat0, lon1, lat1))
    assert len(part) == 1 and 20 * 20 * 100.0 <= part.area[0] < 80 * 20 * 100.0
    assert X0 + 15 * PIXEL < part.x[0] < X0 + 31 * PIXEL


def test_class_table_chosen_by_name_or_argument(tmp_path: Path) -> None:
    array = np.zeros((20, 20), np.uint8)
    array[2:12, 2:12] = 80            # WorldCover permanent water; CORINE 80 does not exist
    plain = write_raster(tmp_path / "landcover.tif", array)
    with pytest.raises(SourceError, match="--raster-classes"):
        read_landcover(plain, TABLE)
    assert read_landcover(plain, TABLE, classes="worldcover", min_area_m2=0).counts() == {"water": 1}
    assert len(read_landcover(plain, TABLE, classes="corine", min_area_m2=0)) == 0
    wc = write_raster(tmp_path / "my_WorldCover_tile.tif", array)
    assert read_landcover(wc, TABLE, min_area_m2=0).counts() == {"water": 1}
    with pytest.raises(SourceError, match=f"{plain.name}: no raster class table named 'nope'"):
        read_landcover(plain, TABLE, classes="nope")
    assert raster_class_table_name("g100_clc12_V18_5.tif") == "corine"


def test_user_class_table_from_labels_file(tmp_path: Path) -> None:
    labels = tmp_path / "labels.toml"
    labels.write_text('labels = ["lake", "wood"]\n[osm]\nrules = []\n[raster.mine]\n7 = "lake"\n300 = "wood"\n')
    table = load_label_table(labels)
    array = np.zeros((20, 20), np.int16)   # 16-bit codes: 300 does not fit a byte
    array[1:5, 1:5] = 7
    array[10:15, 10:15] = 300
    array[16:19, 1:4] = -3                 # a negative code not in the table
    path = write_raster(tmp_path / "survey.tif", array, nodata=-1)
    objects = read_landcover(path, table, classes="mine", min_area_m2=0.0)
    assert objects.labels == ("lake", "wood")
    assert objects.counts() == {"lake": 1, "wood": 1}
    assert objects.area[objects.names() == "wood"][0] == pytest.approx(25 * PIXEL * PIXEL)


def test_int32_codes(tmp_path: Path) -> None:
    labels = tmp_path / "labels.toml"
    labels.write_text('labels = ["lake"]\n[osm]\nrules = []\n[raster.big]\n100000 = "lake"\n')
    array = np.zeros((10, 10), np.int32)
    array[2:5, 2:6] = 100000
    objects = read_landcover(write_raster(tmp_path / "big.tif", array), load_label_table(labels), classes="big",
                             min_area_m2=0.0)
    assert objects.counts() == {"lake": 1} and objects.area[0] == pytest.approx(12 * PIXEL * PIXEL)


@pytest.mark.parametrize("dtype", ["int8", "uint16", "int16", "int32", "uint32"])
def test_many_codes_any_integer_type(tmp_path: Path, dtype: str) -> None:
    # 20 codes (more than are compared one by one): they go through a lookup table or a sorted search.
    info = np.iinfo(dtype)
    codes = [int(c) for c in np.linspace(max(info.min, -100_000), min(info.max, 100_000), 20).astype(dtype)]
    body = "\n".join(f'"{c}" = "{"lake" if i % 2 else "wood"}"' for i, c in enumerate(codes))
    labels = tmp_path / "labels.toml"
    labels.write_text(f'labels = ["lake", "wood"]\n[osm]\nrules = []\n[raster.many]\n{body}\n')
    not_in_table = [c for c in (codes[1] - 1, codes[1] + 1, codes[2] + 1) if c not in codes]
    array = np.full((30, 30), not_in_table[0], dtype)
    array[0:10, 0:10] = codes[0]     # wood
    array[0:10, 10:20] = codes[2]    # wood, touching: one patch with the first
    array[20:30, 20:30] = codes[1]   # lake
    array[20:25, 0:5] = not_in_table[1]
    objects = read_landcover(write_raster(tmp_path / "many.tif", array), load_label_table(labels), classes="many",
                             min_area_m2=0.0)
    assert sorted(zip(objects.names().tolist(), objects.area.tolist())) == [("lake", 100 * PIXEL * PIXEL),
                                                                            ("wood", 200 * PIXEL * PIXEL)]


def test_raster_suffixes() -> None:
    assert all(is_raster_path(f"a{s}") for s in RASTER_SUFFIXES)
    assert is_raster_path("A.TIF") and not is_raster_path("a.geojson") and not is_raster_path("a.osm.pbf")


# ---------------------------------------------------------------- bad input


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MapdbIOError, match="no such file"):
        read_landcover(tmp_path / "clc_missing.tif", TABLE)


def test_raster_without_crs(tmp_path: Path) -> None:
    path = write_raster(tmp_path / "clc_nocrs.tif", np.ones((10, 10), np.uint8), crs=None)
    with pytest.raises(SourceError, match=r"clc_nocrs\.tif: raster has no CRS$"):
        read_landcover(path, TABLE)


def test_not_a_raster(tmp_path: Path) -> None:
    path = tmp_path / "clc_text.tif"
    path.write_text("this is not a GeoTIFF\n")
    with pytest.raises(SourceError, match=r"clc_text\.tif: not a readable raster \("):
        read_landcover(path, TABLE)


@pytest.mark.parametrize("keep", [0.5, 0.02])
def test_truncated_raster(tmp_path: Path, keep: float) -> None:
    rng = np.random.default_rng(1)
    full = write_raster(tmp_path / "full.tif", rng.integers(1, 45, (300, 300)).astype(np.uint8), block_rows=16)
    data = full.read_bytes()
    path = tmp_path / "clc_truncated.tif"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(SourceError, match=r"clc_truncated\.tif: not a readable raster \(") as info:
        read_landcover(path, TABLE)
    assert "\n" not in str(info.value)


def test_float_raster(tmp_path: Path) -> None:
    path = write_raster(tmp_path / "clc_float.tif", np.ones((10, 10), np.float32))
    with pytest.raises(SourceError, match="float32.*integers"):
        read_landcover(path, TABLE)


def test_multiband_raster(tmp_path: Path) -> None:
    path = write_raster(tmp_path / "clc_rgb.tif", np.ones((3, 10, 10), np.uint8))
    with pytest.raises(SourceError, match="3 bands"):
        read_landcover(path, TABLE)


# ---------------------------------------------------------------- real data


def _real(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"real data absent: {path} (expected ../shared/data beside the checkout)")
    return path


def _reference_patches(path: Path) -> list[tuple[str, float, float, float]]:
    """Whole-array labelling of a small projected raster, label by label, as an independent check."""
    classes = TABLE.raster_classes("corine")
    with rasterio.open(path) as src:
        codes, t, nodata = src.read(1), src.transform, src.nodata
    label_of = np.full(256, "", dtype=object)
    for code, name in classes.items():
        if code != nodata:
            label_of[code] = name
    names = label_of[codes]
    pixel_area = abs(t.a * t.e)
    out = []
    for name in sorted(set(classes.values())):
        comp, n = ndimage.label(names == name, structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        count = np.bincount(comp.ravel())[1:]
        rows = ndimage.sum_labels(np.indices(comp.shape)[0], comp, np.arange(1, n + 1)) / count
        cols = ndimage.sum_labels(np.indices(comp.shape)[1], comp, np.arange(1, n + 1)) / count
        for k in np.flatnonzero(count * pixel_area >= 10_000.0):
            x, y = t @ (cols[k] + 0.5, rows[k] + 0.5)
            out.append((name, round(x, 3), round(y, 3), round(count[k] * pixel_area, 3)))
    return sorted(out)


# The tiled reads of a whole real raster are slow (2-4 s each): the default run checks the untiled read, `-m slow`
# the tilings too (small tilings are checked on generated rasters in every run).
@pytest.mark.parametrize("tile", [None, pytest.param((7, 100), marks=pytest.mark.slow),
                                  pytest.param((50, 37), marks=pytest.mark.slow)])
@pytest.mark.parametrize("name", sorted(CORINE_FILES))
def test_real_corine_rasters(name: str, tile) -> None:
    path = _real(name)
    objects = read_landcover(path, TABLE, _tile=tile)  # many tile edges on real data
    assert objects.crs == CORINE_FILES[name]
    counts = objects.counts()
    assert counts["forest"] > 50 and counts["built_up"] > 20 and counts["farmland"] > 10
    assert objects.area.min() >= 10_000.0
    with rasterio.open(path) as src:
        b = src.bounds
    assert ((objects.x > b.left) & (objects.x < b.right) & (objects.y > b.bottom) & (objects.y < b.top)).all()
    got = sorted(zip(objects.names().tolist(), np.round(objects.x, 3).tolist(), np.round(objects.y, 3).tolist(),
                     np.round(objects.area, 3).tolist(), strict=True))
    assert got == _reference_patches(path)


def test_real_corine_bern_valais_has_glaciers() -> None:
    objects = read_landcover(_real("corine2000_bern_valais_g100_clc00.tif"), TABLE)
    counts = objects.counts()
    assert counts["snow_ice"] > 50           # the Bernese and Valais Alps
    # The largest glacier patch (Aletsch region) is well over 50 km^2.
    assert objects.area[objects.names() == "snow_ice"].max() > 50e6


def test_real_worldcover_window() -> None:
    # São Tomé town and its surroundings, read through a small lon/lat window of the 36000^2 tile.
    bbox = (6.6, 0.25, 6.75, 0.4)
    objects = read_landcover(_real(WORLDCOVER), TABLE, bbox=bbox)
    assert objects.crs == "EPSG:4326"
    assert objects.counts().get("built_up", 0) >= 5 and objects.counts().get("forest", 0) >= 5
    assert ((objects.x >= bbox[0]) & (objects.x <= bbox[2]) & (objects.y >= bbox[1]) & (objects.y <= bbox[3])).all()
    # 10 m pixels at the equator are 85.5 m^2 ... 100 m^2 patches need >= 117 pixels.
    assert objects.area.min() >= 10_000.0
