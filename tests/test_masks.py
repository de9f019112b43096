"""Masks and COCO detections to image objects: exact centroids, areas, boxes, border flags, bad input."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import Affine
from scipy import ndimage

from mapdb.classmap import load_class_table
from mapdb.detections.coco import decode_rle, encode_rle, from_coco
from mapdb.detections.images import parse_image
from mapdb.detections.masks import from_mask, mask_document, read_mask
from mapdb.errors import ImageInputError, LabelTableError, MapdbIOError
from mapdb.labels import default_label_table

LABELS = default_label_table().labels


def objects_of(doc):
    return [(o["label"], o["x"], o["y"], o["area_px"], o["border"], o["bbox"]) for o in doc["objects"]]


def test_exact_centroid_area_and_box_of_shapes() -> None:
    mask = np.zeros((20, 30), np.uint8)
    mask[2:5, 5:9] = 1                       # 3 rows x 4 columns: centre (7, 3.5)
    mask[10, 10:13] = 2                      # an L: (10,10) (10,11) (10,12) (11,10) (12,10)
    mask[11:13, 10] = 2
    doc = from_mask(mask, {1: "building", 2: "water"}, image_id="shapes")
    assert doc["id"] == "shapes" and (doc["width"], doc["height"]) == (30, 20)
    rows, cols = np.nonzero(mask == 2)
    assert objects_of(doc) == [
        ("building", 7.0, 3.5, 12, False, [5, 2, 9, 5]),
        ("water", round(cols.mean() + 0.5, 3), round(rows.mean() + 0.5, 3), 5, False, [10, 10, 13, 13]),
    ]
    assert doc["skipped_classes"] == {}
    # The document is a valid query input, and the query reads the new fields.
    image = parse_image(doc)
    assert image.area_px.tolist() == [12, 5] and image.border.tolist() == [False, False]
    assert image.bbox.tolist() == [[5, 2, 9, 5], [10, 10, 13, 13]]


def test_single_pixel_centroid_is_its_centre() -> None:
    mask = np.zeros((5, 5), bool)
    mask[0, 4] = True
    (obj,) = from_mask(mask, {1: "building"}, min_area=1)["objects"]
    assert (obj["x"], obj["y"], obj["area_px"], obj["bbox"], obj["border"]) == (4.5, 0.5, 1, [4, 0, 5, 1], True)


def test_random_regions_agree_with_scipy_center_of_mass() -> None:
    rng = np.random.default_rng(5)
    mask = (ndimage.gaussian_filter(rng.random((120, 160)), 3) > 0.52).astype(np.uint8) * 3
    doc = from_mask(mask, {3: "building"}, min_area=1)
    labelled, n = ndimage.label(mask == 3, structure=np.ones((3, 3)))
    assert n > 10 and len(doc["objects"]) == n
    centres = ndimage.center_of_mass(mask == 3, labelled, range(1, n + 1))
    areas = ndimage.sum_labels(mask == 3, labelled, range(1, n + 1))
    for obj, (row, col), area in zip(doc["objects"], centres, areas, strict=True):
        assert obj["x"] == pytest.approx(col + 0.5, abs=1e-3) and obj["y"] == pytest.approx(row + 0.5, abs=1e-3)
        assert obj["area_px"] == area


@pytest.mark.parametrize("turn_deg", [0.0, 30.0, 90.0, 135.0, 179.0])
def test_major_axis_and_elongation_of_a_turned_rectangle(turn_deg: float) -> None:
    """A 90 x 30 px rectangle turned counter-clockwise (y up) by ``turn_deg``: its blob's major axis is that
    angle and its elongation 3 (sqrt of the moments' ratio, 90^2 / 30^2); a square's is 1 and a one-pixel line
    of 50 pixels is 50 long."""
    rows, cols = np.mgrid[0:300, 0:300] + 0.5
    along = np.array([np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))])
    dx, dy = cols - 150.0, -(rows - 150.0)  # y up
    u, v = dx * along[0] + dy * along[1], -dx * along[1] + dy * along[0]
    mask = ((np.abs(u) <= 45) & (np.abs(v) <= 15)).astype(np.uint8)
    mask[5:25, 5:25] = 2  # a square, away from the rectangle
    mask[240:290, 290] = 3  # a vertical line one pixel wide
    doc = from_mask(mask, {1: "building", 2: "park", 3: "water"})
    rect, square, line = (next(o for o in doc["objects"] if o["label"] == name)
                          for name in ("building", "park", "water"))
    assert abs((rect["orientation_deg"] - turn_deg + 90) % 180 - 90) < 0.5
    assert rect["elongation"] == pytest.approx(3.0, rel=0.02)
    assert square["elongation"] == pytest.approx(1.0, abs=1e-3)
    assert line["orientation_deg"] == 90.0 and line["elongation"] == pytest.approx(50.0, rel=1e-3)
    assert all(0 <= o["orientation_deg"] < 180 for o in doc["objects"])


def test_four_and_eight_connectivity() -> None:
    mask = np.zeros((6, 6), np.uint8)
    mask[1, 1] = mask[2, 2] = mask[3, 3] = 1  # a diagonal line: one region by corners, three by edges
    eight = from_mask(mask, {1: "building"}, min_area=1)["objects"]
    four = from_mask(mask, {1: "building"}, min_area=1, connectivity=4)["objects"]
    assert [(o["x"], o["y"], o["area_px"]) for o in eight] == [(2.5, 2.5, 3)]
    assert [(o["x"], o["y"], o["area_px"]) for o in four] == [(1.5, 1.5, 1), (2.5, 2.5, 1), (3.5, 3.5, 1)]
    with pytest.raises(ValueError, match="connectivity must be 4 or 8"):
        from_mask(mask, {1: "building"}, connectivity=6)


def test_border_flag_on_each_edge() -> None:
    mask = np.zeros((10, 10), np.uint8)
    mask[0, 4:6] = 1        # top
    mask[4:6, 0] = 1        # left
    mask[9, 4:6] = 1        # bottom
    mask[4:6, 9] = 1        # right
    mask[4:6, 4:6] = 1      # inside
    doc = from_mask(mask, {1: "building"}, min_area=1, connectivity=4)
    flags = {(o["x"], o["y"]): o["border"] for o in doc["objects"]}
    assert flags == {(5.0, 0.5): True, (0.5, 5.0): True, (5.0, 5.0): False, (9.5, 5.0): True, (5.0, 9.5): True}


def test_min_area_and_touching_classes_stay_apart() -> None:
    mask = np.zeros((8, 8), np.uint8)
    mask[1, 1:4] = 1          # 3 px
    mask[5:7, 2:4] = 1        # 4 px of class 1 ...
    mask[5:7, 4:6] = 2        # ... touching 4 px of class 2: two objects, not one
    doc = from_mask(mask, {1: "building", 2: "park"})          # default min_area 4
    assert [(o["label"], o["x"], o["y"]) for o in doc["objects"]] == [("building", 3.0, 6.0), ("park", 5.0, 6.0)]
    assert len(from_mask(mask, {1: "building", 2: "park"}, min_area=3)["objects"]) == 3
    assert len(from_mask(mask, {1: "building", 2: "park"}, min_area=5)["objects"]) == 0


def test_unknown_classes_skipped_and_counted_background_mappable() -> None:
    mask = np.full((4, 4), 7, np.uint16)
    mask[:2, :2] = 0
    mask[3, 3] = 1
    doc = from_mask(mask, {1: "building"}, min_area=1)
    assert doc["skipped_classes"] == {"7": 11} and len(doc["objects"]) == 1
    doc0 = from_mask(mask, {0: "water"}, min_area=1)  # code 0 is background only unless mapped
    assert [(o["label"], o["area_px"], o["x"], o["y"]) for o in doc0["objects"]] == [("water", 4, 1.0, 1.0)]
    assert doc0["skipped_classes"] == {"1": 1, "7": 11}
    # Codes far apart (a 32-bit instance id image) take the sorting path and give the same answer.
    wide = mask.astype(np.int64)
    wide[wide == 7] = 4_000_000_000
    assert from_mask(wide, {1: "building"}, min_area=1)["skipped_classes"] == {"4000000000": 11}
    signed = np.array([[-128, 127], [0, -128]], np.int8)  # negative codes, counted without overflow
    doc8 = from_mask(signed, {-128: "building"}, min_area=1)
    assert objects_of(doc8) == [("building", 1.0, 1.0, 2, True, [0, 0, 2, 2])] and doc8["skipped_classes"] == {"127": 1}


def test_empty_mask_and_camera_fields() -> None:
    doc = from_mask(np.zeros((3, 4), np.uint8), {1: "building"}, fov_deg=60, attitude=(1.0, -2.0), altitude=120)
    assert doc["objects"] == [] and doc["skipped_classes"] == {}
    assert doc["camera"] == {"fov_deg": 60.0} and doc["altitude_m"] == 120.0
    assert doc["attitude"] == {"roll_deg": 1.0, "pitch_deg": -2.0}
    image = parse_image(doc)
    assert (image.fov_deg, image.roll_deg, image.pitch_deg, image.altitude_m) == (60.0, 1.0, -2.0, 120.0)
    assert image.area_px is None and image.border is None
    assert "camera" not in from_mask(np.zeros((3, 4), np.uint8), {})


@pytest.mark.parametrize(("mask", "message"), [
    (np.zeros((2, 3, 3), np.uint8), "a mask must be a 2-D image, got 3 dimensions"),
    (np.full((3, 3), 0.5), "pixels are not whole numbers"),
    (np.array([["a"]]), "pixels of type <U1"),
    (np.zeros((0, 3), np.uint8), "a 3x0 mask; each side must be 1 to"),
])
def test_bad_arrays_are_one_line_errors(mask, message) -> None:
    with pytest.raises(ImageInputError, match=message) as err:
        from_mask(mask, {1: "building"}, source="m.png")
    assert str(err.value).startswith("m.png: ") and "\n" not in str(err.value)


def test_camera_value_out_of_range() -> None:
    with pytest.raises(ImageInputError, match=r"m: camera\.fov_deg: 200\.0 is greater than or equal"):
        from_mask(np.zeros((3, 3), np.uint8), {}, fov_deg=200, source="m")


def test_integral_float_masks_accepted() -> None:
    mask = np.zeros((4, 4), np.float32)
    mask[1:3, 1:3] = 1.0
    assert objects_of(from_mask(mask, {1: "building"})) == [("building", 2.0, 2.0, 4, False, [1, 1, 3, 3])]


# --- mask files -----------------------------------------------------------------------------------


def write_raster(path: Path, bands: np.ndarray, *, driver: str = "GTiff", georef: bool = False) -> Path:
    """A mask file of one or more bands; with ``georef``, 0.5 m pixels from the corner (500000, 5000000) UTM 31N."""
    bands = bands if bands.ndim == 3 else bands[None]
    extra = {"crs": "EPSG:32631", "transform": Affine(0.5, 0.0, 500_000.0, 0.0, -0.5, 5_000_000.0)} if georef else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return _write_raster(path, bands, driver, extra)


def _write_raster(path: Path, bands: np.ndarray, driver: str, extra: dict) -> Path:
    with rasterio.open(path, "w", driver=driver, width=bands.shape[2], height=bands.shape[1], count=bands.shape[0],
                       dtype=bands.dtype, **extra) as ds:
        ds.write(bands)
    return path


def test_png_single_class_mask_and_geotiff_georeference(tmp_path: Path) -> None:
    mask = np.zeros((40, 60), np.uint8)
    mask[10:20, 10:30] = 255
    png = write_raster(tmp_path / "m.png", mask, driver="PNG")
    doc = mask_document(png, label="building")
    assert objects_of(doc) == [("building", 20.0, 15.0, 200, False, [10, 10, 30, 20])]
    assert doc["id"] == str(png) and "georef" not in doc
    tif = write_raster(tmp_path / "m.tif", mask, georef=True)
    georef = mask_document(tif, {255: "building"})["georef"]
    # The image centre (30, 20) px at 0.5 m from the corner (500000, 5000000), north up.
    assert georef["crs"] == "EPSG:32631" and georef["heading_deg"] == 0.0 and georef["m_per_px"] == 0.5
    assert (georef["x"], georef["y"]) == (500_015.0, 4_999_990.0)
    assert georef["lon"] == pytest.approx(3.0, abs=0.01) and georef["lat"] == pytest.approx(45.1, abs=0.1)


def test_grey_saved_as_rgb_is_one_band_colour_is_refused(tmp_path: Path) -> None:
    mask = np.zeros((8, 8), np.uint8)
    mask[2:6, 2:6] = 1
    grey = write_raster(tmp_path / "grey.png", np.stack([mask, mask, mask]), driver="PNG")
    assert read_mask(grey).array.tolist() == mask.tolist()
    colour = write_raster(tmp_path / "colour.png", np.stack([mask, mask * 2, mask]), driver="PNG")
    with pytest.raises(ImageInputError, match=r"colour\.png: 3 different bands; a mask has one band"):
        read_mask(colour)


def test_mask_file_errors(tmp_path: Path) -> None:
    text = tmp_path / "notes.png"
    text.write_text("not an image\n")
    with pytest.raises(ImageInputError, match=r"notes\.png: not an image that GDAL can read \(") as err:
        read_mask(text)
    assert str(tmp_path) not in str(err.value).split(": ", 1)[1]  # the path is named once, at the start
    with pytest.raises(MapdbIOError, match=r"nope\.png: no such mask"):
        read_mask(tmp_path / "nope.png")
    with pytest.raises(MapdbIOError, match="is a directory, not a mask"):
        read_mask(tmp_path)


# --- class tables ---------------------------------------------------------------------------------


def test_class_table_codes_names_and_unknown_labels(tmp_path: Path) -> None:
    good = tmp_path / "classes.toml"
    good.write_text('[classes]\n1 = "building"\n"-2" = "water"\nhouse = "building"\n')
    table = load_class_table(good, LABELS)
    assert table.codes == {1: "building", -2: "water"} and table.classes["house"] == "building"
    bad = tmp_path / "bad.toml"
    bad.write_text('[classes]\n1 = "building"\n2 = "watr"\n')
    with pytest.raises(LabelTableError, match=r"bad\.toml: classes\.2: unknown label 'watr' \(labels: building"):
        load_class_table(bad, LABELS)
    for text, message in [('column = "x"\n[classes]\n1 = "building"\n', "column: unknown key"),
                          ("[other]\n", "other: unknown key"), ("x = [\n", "not a valid TOML"),
                          ("[classes]\n", "classes: missing or empty")]:
        bad.write_text(text)
        with pytest.raises(LabelTableError, match=message):
            load_class_table(bad, LABELS)


# --- COCO -----------------------------------------------------------------------------------------


def coco(annotations, width=100, height=80, image_id=7):
    return {"images": [{"id": image_id, "width": width, "height": height, "file_name": "a.jpg"}],
            "categories": [{"id": 1, "name": "house"}, {"id": 2, "name": "car"}, {"id": 5, "name": "pond"}],
            "annotations": [{"image_id": image_id, **a} for a in annotations]}


def test_rle_decoder_on_hand_encoded_strings() -> None:
    # Worked by hand from COCO's format: 5 bits a character from "0" (48), 0x20 = more, 0x10 = sign; the
    # fourth count on is stored minus the count two before.
    assert decode_rle("52203").tolist() == [5, 2, 2, 2, 5]      # the last two stored as 2-2=0 and 5-2=3
    assert decode_rle("T3").tolist() == [100]                    # 100 = 4 + 3*32: "0"+4+0x20, "0"+3
    assert decode_rle("0:1I").tolist() == [0, 10, 1, 3]          # 3-10 = -7: one character, sign bit set
    for bad, message in [("T", "cut short"), ("\x7f", "alphabet"), ("o" * 12 + "0", "64 bits")]:
        with pytest.raises(ValueError, match=message):
            decode_rle(bad)


def test_rle_round_trip_matches_from_mask() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        h, w = rng.integers(1, 40, size=2)
        inst = rng.random((h, w)) < rng.uniform(0.05, 0.9)
        rle = encode_rle(inst)
        runs = decode_rle(rle["counts"])
        assert runs.sum() == h * w
        assert np.array_equal(np.repeat(np.arange(runs.size) % 2 == 1, runs).reshape(w, h).T, inst)
        if not inst.any():
            continue
        (doc,) = from_coco(coco([{"category_id": 1, "segmentation": rle}], int(w), int(h)), {1: "building"},
                           min_area=1)
        # The instance is one object, wherever its pixels lie: compare with its pixels taken together.
        rows, cols = np.nonzero(inst)
        (obj,) = doc["objects"]
        assert obj["x"] == pytest.approx(cols.mean() + 0.5, abs=1e-3)
        assert obj["y"] == pytest.approx(rows.mean() + 0.5, abs=1e-3)
        assert obj["area_px"] == inst.sum()
        assert obj["bbox"] == [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
        uncompressed = {"size": [int(h), int(w)], "counts": runs.tolist()}
        (again,) = from_coco(coco([{"category_id": 1, "segmentation": uncompressed}], int(w), int(h)),
                             {1: "building"}, min_area=1)
        assert again["objects"] == doc["objects"]


def test_polygons_boxes_categories_and_scores() -> None:
    doc_in = coco([
        {"category_id": 1, "segmentation": [[10, 10, 30, 10, 30, 20, 10, 20]], "score": 0.9},   # 20x10 rectangle
        {"category_id": 5, "segmentation": [[40, 40, 70, 40, 40, 70]], "score": 0.8},           # triangle, clipped
        {"category_id": 1, "segmentation": [[0, 0, 4, 0, 4, 4, 0, 4], [6, 0, 8, 0, 8, 2, 6, 2]]},  # two parts
        {"category_id": 1, "bbox": [90, 60, 20, 30], "score": 0.7},                              # box past the edge
        {"category_id": 2, "bbox": [0, 0, 4, 4]},                                                # unmapped: car
        {"category_id": 1, "bbox": [50, 5, 4, 4], "score": 0.1},                                 # low score
    ])
    (doc,) = from_coco(doc_in, {"house": "building", "5": "water"}, min_score=0.5)
    got = [(o["label"], o["x"], o["y"], o["area_px"], o["border"], o["bbox"], o.get("box", False))
           for o in doc["objects"]]
    # The triangle (40,40)-(70,40)-(40,70) cut by the bottom edge y = 80 is untouched: centroid (50, 50).
    # The two parts: 16 px centred (2, 2) and 4 px centred (7, 1) -> (3, 1.8).
    assert got == [
        ("building", 20.0, 15.0, 200.0, False, [10, 10, 30, 20], False),
        ("water", 50.0, 50.0, 450.0, False, [40, 40, 70, 70], False),
        ("building", 3.0, 1.8, 20.0, True, [0, 0, 8, 4], False),
        ("building", 95.0, 70.0, 200.0, True, [90, 60, 100, 80], True),
    ]
    assert doc["skipped_classes"] == {"car": 1} and doc["skipped_low_score"] == 1
    assert doc["id"] == 7 and doc["file_name"] == "a.jpg"
    parse_image(doc)  # a valid query input


def test_bare_list_of_detections_with_images() -> None:
    detections = [{"image_id": "b", "category_id": 3, "bbox": [10, 10, 10, 10]}]
    images = [{"id": "a", "width": 50, "height": 50}, {"id": "b", "width": 40, "height": 30}]
    docs = from_coco(detections, {3: "building"}, images=images)
    assert [(d["id"], len(d["objects"])) for d in docs] == [("a", 0), ("b", 1)]
    with pytest.raises(ImageInputError, match="a list of detections names no image sizes"):
        from_coco(detections, {3: "building"}, source="det.json")


@pytest.mark.parametrize(("annotation", "message"), [
    ({"image_id": 8, "category_id": 1, "bbox": [0, 0, 1, 1]}, r"annotations\[0\]: image_id 8 is not one of"),
    ({"category_id": 1, "segmentation": {"size": [80, 90], "counts": [7200]}},
     r"segmentation\.size: \[80, 90\] disagrees with its image's height and width \[80, 100\]"),
    ({"category_id": 1, "segmentation": {"size": [80, 100], "counts": [10, 5]}}, "sum to 100x80 pixels"),
    ({"category_id": 1, "segmentation": {"size": [80, 100], "counts": "T"}}, "not COCO's compressed RLE"),
    ({"category_id": 1, "segmentation": [[1, 2, 3]]}, "a polygon needs x, y pairs"),
    ({"category_id": 1, "segmentation": [[1, 2, "x", 4, 5, 6]]}, "must be a list of numbers"),
    ({"category_id": 1, "bbox": [1, 2, -3, 4]}, r"bbox: must be \[x, y, width, height\]"),
    ({"category_id": 1}, "no segmentation and no bbox"),
    ({"category_id": 1, "bbox": [1, 1, 2, 2], "score": "high"}, r"score: must be a number"),
])
def test_bad_coco_annotations(annotation, message) -> None:
    doc = coco([])
    doc["annotations"] = [{"image_id": 7, **annotation}]
    with pytest.raises(ImageInputError, match=message) as err:
        from_coco(doc, {1: "building"}, source="det.json")
    assert str(err.value).startswith("det.json: ") and "\n" not in str(err.value)


def test_bad_coco_files(tmp_path: Path) -> None:
    path = tmp_path / "det.json"
    path.write_text("{not json")
    with pytest.raises(ImageInputError, match=r"det\.json: not a JSON file"):
        from_coco(path, {})
    path.write_text(json.dumps({"images": [{"id": 1, "width": 5, "height": 5}, {"id": 1, "width": 5, "height": 5}],
                                "annotations": []}))
    with pytest.raises(ImageInputError, match=r"images\[1\]: id 1 given twice"):
        from_coco(path, {})
    path.write_text(json.dumps({"images": [{"id": 1, "width": 0, "height": 5}], "annotations": []}))
    with pytest.raises(ImageInputError, match=r"images\[0\]: width and height must be positive integers"):
        from_coco(path, {})
    with pytest.raises(MapdbIOError, match="no such COCO file"):
        from_coco(tmp_path / "none.json", {})
