"""Hostile masks and COCO files for ``mapdb objects``: each gives its documented outcome, never a traceback,
a hang, a silent wrong answer or a partial output, and no input is changed.

Cases: PNGs truncated at every chunk boundary and inside IDAT, a damaged chunk, GeoTIFFs truncated at every
strip, FIFOs and devices, non-finite or absurd georeferencing, COCO polygons over the vertex cap or
crossing themselves; and the strip-wise region sums against scipy on masks cut into many strips.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from maskfiles import write_mask
from rasterio.transform import Affine
from scipy import ndimage

from mapdb.detections import coco, masks
from mapdb.detections.masks import from_mask


def run(*args: str):
    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


def digest(*paths: Path) -> list[str]:
    return [hashlib.sha256(p.read_bytes()).hexdigest() for p in paths]


def noisy_mask(height: int = 240, width: int = 320, seed: int = 1) -> np.ndarray:
    """Blobs over noise: compresses to several PNG IDAT chunks and several GeoTIFF strips."""
    rng = np.random.default_rng(seed)
    blobs = ndimage.gaussian_filter(rng.random((height, width)), 2) > 0.5
    return np.where(blobs | (rng.random((height, width)) < 0.2), 255, 0).astype(np.uint8)


def png_chunk_ends(data: bytes) -> list[int]:
    """Byte offsets where each chunk of a PNG ends (the signature's end first)."""
    ends, position = [8], 8
    while position < len(data):
        (length,) = struct.unpack(">I", data[position:position + 4])
        position += 12 + length
        ends.append(position)
    return ends


def tiff_strips(data: bytes) -> tuple[list[int], list[int]]:
    """Offsets and byte counts of the strips of a little-endian classic TIFF (as GDAL writes them)."""
    assert data[:4] == b"II*\x00"
    (ifd,) = struct.unpack("<I", data[4:8])
    (count,) = struct.unpack("<H", data[ifd:ifd + 2])
    found: dict[int, list[int]] = {}
    for i in range(count):
        tag, kind, n, value = struct.unpack("<HHII", data[ifd + 2 + 12 * i:ifd + 14 + 12 * i])
        if tag in (273, 279):
            size = {3: 2, 4: 4}[kind]
            fmt = "<" + ("H" if size == 2 else "I") * n
            raw = data[value:value + size * n] if size * n > 4 else data[ifd + 10 + 12 * i:ifd + 10 + 12 * i + size * n]
            found[tag] = list(struct.unpack(fmt, raw))
    return found[273], found[279]


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("mapdb: error: ")]


# --- N2: a mask is read whole or refused -----------------------------------------------------------------


def test_png_truncated_at_every_chunk_boundary_and_inside_idat_is_refused_the_batch_goes_on(tmp_path: Path) -> None:
    good = write_mask(tmp_path / "good.png", noisy_mask(seed=2))
    whole = write_mask(tmp_path / "whole.png", noisy_mask()).read_bytes()
    ends = png_chunk_ends(whole)
    assert len(ends) >= 5  # signature, IHDR, several IDAT, IEND: every boundary below is a real one
    cuts = sorted({*ends[:-1], len(whole) - 1, *range(ends[1] + 100, ends[-2], (ends[-2] - ends[1]) // 5)})
    cut_files = []
    for cut in cuts:
        path = tmp_path / f"cut{cut:06d}.png"
        path.write_bytes(whole[:cut])
        cut_files.append(path)
    before = digest(good, *cut_files)
    out = tmp_path / "out.jsonl"
    result = run("objects", *map(str, cut_files), str(good), "--label", "building", "-o", str(out))
    assert result.exit_code == 1
    errors = error_lines(result.stderr)
    assert len(errors) == len(cut_files)
    for path, line in zip(cut_files, errors, strict=True):
        assert line.startswith(f"mapdb: error: {path}: cannot read its pixels (truncated or damaged PNG: "), line
    assert result.stderr.splitlines()[-1] == f"1 images, {len(json.loads(out.read_text())['objects'])} objects -> " \
                                             f"{out}; {len(cut_files)} failed"
    assert [json.loads(line)["id"] for line in out.read_text().splitlines()] == [str(good)]
    assert "Traceback" not in result.output and digest(good, *cut_files) == before


def test_a_single_truncated_png_gives_one_line_and_no_output(tmp_path: Path) -> None:
    whole = write_mask(tmp_path / "whole.png", noisy_mask()).read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(whole[:200])  # the case: the first 200 bytes, inside the first IDAT
    before = digest(cut)
    out = tmp_path / "out.jsonl"
    result = run("objects", str(cut), "--label", "building", "-o", str(out))
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"mapdb: error: {cut}: cannot read its pixels (truncated or damaged PNG: a 'IDAT' chunk runs past the end "
        "of the file (200 bytes))"]
    assert not out.exists() and digest(cut) == before


def png_with_damaged_chunk(whole: bytes, chunk_type: bytes) -> bytes:
    """``whole`` with the CRC of its first ``chunk_type`` chunk flipped (a tEXt chunk is added if asked for)."""
    if chunk_type == b"tEXt":
        body = b"tEXtComment\x00made by a test"
        whole = whole[:33] + struct.pack(">I", len(body) - 4) + body + struct.pack(">I", zlib.crc32(body)) + whole[33:]
    position = 8
    while whole[position + 4:position + 8] != chunk_type:
        position += 12 + struct.unpack(">I", whole[position:position + 4])[0]
    length = struct.unpack(">I", whole[position:position + 4])[0]
    crc_at = position + 8 + length
    return whole[:crc_at] + bytes(b ^ 0xFF for b in whole[crc_at:crc_at + 4]) + whole[crc_at + 4:]


@pytest.mark.parametrize(("chunk", "says"), [(b"IDAT", "libpng"), (b"tEXt", "tEXt: CRC error")])
def test_a_png_with_a_damaged_chunk_is_refused(tmp_path: Path, chunk: bytes, says: str) -> None:
    """A bad CRC in the pixels is a GDAL error; in a text chunk libpng only warns, and the warning refuses it."""
    whole = write_mask(tmp_path / "whole.png", noisy_mask()).read_bytes()
    bad = tmp_path / "bad.png"
    bad.write_bytes(png_with_damaged_chunk(whole, chunk))
    out = tmp_path / "out.jsonl"
    result = run("objects", str(bad), "--label", "building", "-o", str(out))
    assert result.exit_code == 1 and len(result.stderr.splitlines()) == 1
    (line,) = error_lines(result.stderr)
    assert line.startswith(f"mapdb: error: {bad}: cannot read its pixels (") and says in line, line
    assert not out.exists()


@pytest.mark.parametrize("compress", ["none", "deflate"])
def test_geotiff_truncated_at_every_strip_is_refused(tmp_path: Path, compress: str) -> None:
    whole = write_mask(tmp_path / "whole.tif", noisy_mask(), compress=compress, blockysize=16).read_bytes()
    offsets, sizes = tiff_strips(whole)
    assert len(offsets) >= 10
    cuts = sorted({8, 100, *offsets, *(o + s // 2 for o, s in zip(offsets, sizes, strict=True)), len(whole) - 1})
    cuts = [c for c in cuts if c < len(whole)]
    cut_files = []
    for cut in cuts:
        path = tmp_path / f"cut{cut:07d}.tif"
        path.write_bytes(whole[:cut])
        cut_files.append(path)
    before = digest(*cut_files)
    out = tmp_path / "out.jsonl"
    result = run("objects", *map(str, cut_files), "--label", "building", "-o", str(out))
    assert result.exit_code == 1 and result.stderr.splitlines() == error_lines(result.stderr)
    for path, line in zip(cut_files, error_lines(result.stderr), strict=True):
        assert line.startswith((f"mapdb: error: {path}: cannot read its pixels (",
                                f"mapdb: error: {path}: not an image that GDAL can read (")), line
    assert not out.exists() and digest(*cut_files) == before


# --- N8: special files are refused before they are opened ------------------------------------------------


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_fifo_and_device_are_refused_before_opening(tmp_path: Path) -> None:
    fifo = tmp_path / "mask.png"
    os.mkfifo(fifo)
    out = tmp_path / "out.jsonl"
    # A fresh process with a timeout: were the FIFO opened, the command would wait for a writer forever.
    result = subprocess.run([sys.executable, "-m", "mapdb_cli", "objects", str(fifo), "--label", "building",
                             "-o", str(out)], capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stderr, result.stdout) == (1, f"mapdb: error: {fifo}: not a regular file\n", "")
    assert not out.exists()
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\n1 = "building"\n')
    result = subprocess.run([sys.executable, "-m", "mapdb_cli", "objects", "--coco", str(fifo), "--classes",
                             str(classes), "-o", str(out)], capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stderr) == (1, f"mapdb: error: {fifo}: not a regular file\n")
    assert not out.exists()
    if Path("/dev/zero").exists():
        result = run("objects", "/dev/zero", "--label", "building", "-o", str(out))
        assert (result.exit_code, result.stderr) == (1, "mapdb: error: /dev/zero: not a regular file\n")
        assert not out.exists()


# --- N7: georeferencing that cannot be right is dropped with a warning ------------------------------------


@pytest.mark.parametrize(("crs", "transform", "problem"), [
    ("EPSG:32631", Affine(float("nan"), 0.0, 500_000.0, 0.0, -0.5, 5_000_000.0),
     "its pixel size or position is not finite"),
    ("EPSG:32631", Affine(0.5, 0.0, 1e30, 0.0, -0.5, 1e30), "its centre is more than 1e+08 from the origin of its CRS"),
    ("EPSG:32631", Affine(0.5, 0.0, float("inf"), 0.0, -0.5, 0.0), "its pixel size or position is not finite"),
    ("EPSG:32631", Affine(5e6, 0.0, 500_000.0, 0.0, -5e6, 5_000_000.0),
     "its centre has no finite longitude and latitude"),
    ("EPSG:3857", Affine(2e6, 0.0, -3e7, 0.0, -2e6, 2e7), "a pixel of 2e+06 m"),
    ("EPSG:32631", Affine(0.5, 0.0, 500_000.0, 1.0, 0.0, 5_000_000.0), "its pixels have no area"),
])
def test_absurd_georeference_is_dropped_with_a_warning(tmp_path: Path, crs: str, transform: Affine,
                                                       problem: str) -> None:
    mask = np.zeros((20, 30), np.uint8)
    mask[5:10, 5:15] = 1
    tif = write_mask(tmp_path / "m.tif", mask, crs=crs, transform=transform)
    plain = write_mask(tmp_path / "plain.tif", mask)
    before = digest(tif)
    out, expected = tmp_path / "out.jsonl", tmp_path / "expected.jsonl"
    result = run("objects", str(tif), "--label", "building", "-o", str(out))
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines() == [f"mapdb: warning: {tif}: georeference dropped: {problem}",
                                          f"1 images, 1 objects -> {out}"]
    assert run("objects", str(plain), "--label", "building", "-o", str(expected), "-q").exit_code == 0
    doc, reference = json.loads(out.read_text()), json.loads(expected.read_text())
    assert "georef" not in doc and doc["objects"] == reference["objects"] and digest(tif) == before


def test_a_plausible_georeference_is_kept(tmp_path: Path) -> None:
    mask = np.zeros((20, 30), np.uint8)
    mask[5:10, 5:15] = 1
    tif = write_mask(tmp_path / "m.tif", mask, crs="EPSG:32631",
                     transform=Affine(0.5, 0.0, 500_000.0, 0.0, -0.5, 5_000_000.0))
    result = run("objects", str(tif), "--label", "building", "-q")
    assert result.exit_code == 0 and result.stderr == ""
    assert json.loads(result.stdout)["georef"]["m_per_px"] == 0.5


# --- N3: labels and sums in strips give what whole-image sums give ----------------------------------------


@pytest.mark.parametrize("chunk", [1 << 18, 4096, 64])
def test_strip_sums_agree_with_scipy_whatever_the_strip(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    """Regions crossing many strips, and one region spanning them all beside hundreds of small ones (its label
    range is far wider than a strip's runs: counted with np.add.at)."""
    monkeypatch.setattr(masks, "_CHUNK", chunk)
    rng = np.random.default_rng(7)
    mask = (ndimage.gaussian_filter(rng.random((300, 200)), 4) > 0.5).astype(np.uint8)
    mask[:, 0] = 1  # a column touching every strip: one region from first row to last
    labelled, n = ndimage.label(mask, structure=np.ones((3, 3)))
    doc = from_mask(mask, {1: "building"}, min_area=1)
    assert n > 20 and len(doc["objects"]) == n
    centres = ndimage.center_of_mass(mask, labelled, range(1, n + 1))
    boxes = ndimage.find_objects(labelled)
    for obj, (row, col), box, i in zip(doc["objects"], centres, boxes, range(1, n + 1), strict=True):
        assert obj["area_px"] == int((labelled == i).sum())
        assert obj["x"] == round(col + 0.5, 3) and obj["y"] == round(row + 0.5, 3)
        assert obj["bbox"] == [box[1].start, box[0].start, box[1].stop, box[0].stop]


def test_too_many_objects_counted_over_every_class(monkeypatch: pytest.MonkeyPatch) -> None:
    """Over the limit in the first class, the other classes' regions are still counted: the message is exact."""
    monkeypatch.setattr(masks, "MAX_OBJECTS", 15)
    mask = np.zeros((40, 60), np.uint8)
    for code, row in ((1, 2), (2, 18), (3, 34)):
        mask[row:row + 3, 2:58:6] = code  # 10 objects of 3x1 px per class
    with pytest.raises(masks.ImageInputError) as err:
        from_mask(mask, {1: "building", 2: "water", 3: "park"}, min_area=1, source="m.png")
    assert str(err.value) == "m.png: 30 objects, more than the 15 a query accepts; raise the minimum area"


def test_mask_claiming_too_many_bytes_is_refused_before_reading(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(masks, "MAX_MASK_BYTES", 1000)
    tif = write_mask(tmp_path / "wide.tif", np.zeros((20, 20), np.float32))  # 1600 bytes of pixels
    with pytest.raises(masks.ImageInputError, match=r"wide\.tif: a 20x20 mask of float32 is more than the "):
        masks.read_mask(tif)


# --- N6: COCO polygons in linear time, capped -------------------------------------------------------------


def coco_file(path: Path, polygons: list[list[float]], width: int = 400, height: int = 300) -> Path:
    annotations = [{"id": i, "image_id": 1, "category_id": 1, "segmentation": [p]} for i, p in enumerate(polygons)]
    path.write_text(json.dumps({"images": [{"id": 1, "width": width, "height": height}],
                                "annotations": annotations}))
    return path


def test_polygon_over_the_vertex_cap_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(coco, "MAX_POLYGON_VERTICES", 1000)
    turn = np.linspace(0, 2 * np.pi, 1001, endpoint=False)
    ring = np.c_[200 + 100 * np.cos(turn), 150 + 100 * np.sin(turn)].ravel().round(3).tolist()
    path = coco_file(tmp_path / "big.json", [ring[:2000], ring])  # 1000 vertices pass, 1001 do not
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\n1 = "building"\n')
    before = digest(path)
    out = tmp_path / "out.jsonl"
    result = run("objects", "--coco", str(path), "--classes", str(classes), "-o", str(out))
    assert (result.exit_code, result.stderr.splitlines()) == (1, [
        f"mapdb: error: {path}: annotations[1].segmentation: 1,001 vertices, more than the 1,000 a polygon "
        "annotation may have"])
    assert not out.exists() and digest(path) == before


def test_polygons_agree_with_the_exact_overlay(tmp_path: Path) -> None:
    """Simple polygons, either turn, some cut by the image's edges and corners, some with a second part apart:
    the linear-time integrals give GEOS's area, centroid and box."""
    rng = np.random.default_rng(11)
    polygons, expected = [], []
    while len(polygons) < 60:
        n = int(rng.integers(3, 30))
        turn = np.sort(rng.uniform(0, 2 * np.pi, n))[::1 if len(polygons) % 2 else -1]
        radius = rng.uniform(5, 60, n)
        ring = np.c_[rng.uniform(-30, 430) + radius * np.cos(turn), rng.uniform(-30, 330) + radius * np.sin(turn)]
        parts = [ring] if len(polygons) % 3 else [ring, ring + (500.0, 0.0)]
        if not all(shapely.is_valid(shapely.Polygon(p)) for p in parts):
            continue
        exact = shapely.intersection(shapely.union_all([shapely.Polygon(p) for p in parts]),
                                     shapely.box(0, 0, 400, 300))
        if shapely.area(exact) < 4:
            continue
        polygons.append([p.ravel().tolist() for p in parts])
        expected.append(exact)
    doc = coco.from_coco({"images": [{"id": 1, "width": 400, "height": 300}],
                          "annotations": [{"image_id": 1, "category_id": 1, "segmentation": p} for p in polygons]},
                         {1: "building"})[0]
    assert len(doc["objects"]) == len(expected)
    for obj, exact in zip(doc["objects"], expected, strict=True):
        centre = shapely.centroid(exact)
        assert obj["x"] == round(shapely.get_x(centre), 3) and obj["y"] == round(shapely.get_y(centre), 3)
        assert obj["area_px"] == round(shapely.area(exact), 2)
        assert obj["bbox"] == coco._edge_box(shapely.bounds(exact), 400, 300)


def test_self_crossing_polygons_are_answered_at_once(tmp_path: Path) -> None:
    """Winding numbers: a figure eight's equal lobes cancel (no object); a bowtie with a larger lobe has its
    centroid, by winding number, outside it: refused with one line naming the annotation.  GEOS took minutes
    to repair a scribble of 200 random vertices; each below is answered (an object inside its box, or the
    refusal)."""
    image = {"id": 1, "width": 400, "height": 300}
    eight = [0.0, 0.0, 100.0, 100.0, 100.0, 0.0, 0.0, 100.0]
    doc = coco.from_coco({"images": [image], "annotations": [{"image_id": 1, "category_id": 1,
                                                              "segmentation": [eight]}]}, {1: "building"})[0]
    assert doc["objects"] == []
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\n1 = "building"\n')
    bowtie = coco_file(tmp_path / "bowtie.json", [eight, [0.0, 0.0, 200.0, 100.0, 200.0, 10.0, 0.0, 100.0]])
    out = tmp_path / "out.jsonl"
    result = run("objects", "--coco", str(bowtie), "--classes", str(classes), "-o", str(out))
    assert (result.exit_code, result.stderr.splitlines()) == (1, [
        f"mapdb: error: {bowtie}: annotations[1].segmentation: a polygon crossing itself (its centroid by winding "
        "number falls outside it); give simple polygons"])
    assert not out.exists()
    rng = np.random.default_rng(0)
    outcomes = set()
    for _ in range(50):
        scribble = (rng.random(400) * 300).tolist()
        try:
            found = coco._polygon_object([scribble], 400, 300, "a")
        except coco.ImageInputError as err:
            assert str(err).endswith("a polygon crossing itself (its centroid by winding number falls outside it); "
                                     "give simple polygons")
            outcomes.add("refused")
            continue
        assert found is not None
        x, y, _, (x0, y0, x1, y1) = found
        assert x0 <= x <= x1 and y0 <= y <= y1
        outcomes.add("answered")
    assert outcomes == {"refused", "answered"}


@pytest.mark.parametrize("compressed", [False, True])
def test_rle_over_the_count_cap_is_one_line(monkeypatch: pytest.MonkeyPatch, compressed: bool) -> None:
    monkeypatch.setattr(coco, "MAX_RLE_COUNTS", 50)
    mask = np.zeros((30, 40), bool)
    mask[::2, ::3] = True  # many runs
    counts = coco.encode_rle(mask)["counts"] if compressed else [1] * 1200
    ann = {"image_id": 1, "category_id": 1, "segmentation": {"size": [30, 40], "counts": counts}}
    with pytest.raises(coco.ImageInputError) as err:
        coco.from_coco({"images": [{"id": 1, "width": 40, "height": 30}], "annotations": [ann]}, {1: "building"},
                       source="c.json")
    assert str(err.value) == (f"c.json: annotations[0].segmentation.counts: {len(counts):,} counts or characters, "
                              "more than the 50 an RLE mask may have")
