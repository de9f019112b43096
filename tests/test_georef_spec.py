"""``docs/georef.md`` read against the code: the answer's fields, the worked example's transform, footprint
and world file, the level affine's formulas, the world file names and the GeoJSON properties."""

from __future__ import annotations

import ast
import cmath
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from mapdb.detections.images import parse_image
from mapdb.localize import localize
from mapdb.localize.records import georef_fields
from mapdb.localize.worldfile import aux_xml_text, world_file_name, world_file_text
from mapdb.mapfile.queries import MemoryMap
from mapdb.simulation.simulate import paper_map, simulate_images

DOC = (Path(__file__).resolve().parents[1] / "docs" / "georef.md").read_text(encoding="utf-8")


def _section(title: str) -> str:
    start = DOC.index(f"## {title}")
    end = DOC.find("\n## ", start + 1)
    return DOC[start:end if end > 0 else None]


def _table_first_column(section: str) -> list[str]:
    rows = [line for line in section.splitlines() if line.startswith("| `")]
    return [re.match(r"\| `([^`]+)`", row).group(1) for row in rows]  # type: ignore[union-attr]


@pytest.fixture(scope="module")
def answer():
    m = MemoryMap(paper_map(seed=2))
    (image,) = simulate_images(m, 1, pixel_std=1.0, yaw="random", seed=9)
    found = localize(image, m)
    assert found.ok
    return found


def test_the_documented_fields_are_the_ones_written_in_that_place(answer) -> None:
    record = list(answer.to_json())
    documented = _table_first_column(_section("The answer's fields"))
    start = record.index("levelled") + 1
    assert record[start:start + len(documented)] == documented
    assert record[start + len(documented)] == "candidates"


def test_the_worked_example() -> None:
    blocks = re.findall(r"```\n(.*?)```", _section("Worked example"), re.S)
    values = dict(line.split(": ", 1) for line in blocks[0].strip().splitlines())
    pose = {name: float(value) for name, value in (item.split() for item in values["pose"].split(", "))}
    a = pose["scale_m_per_px"] * cmath.exp(-1j * math.radians(pose["heading_deg"]))
    image = parse_image({"width": pose["width"], "height": pose["height"], "objects": []}, "doc")
    fields = georef_fields("EPSG:32631", a, complex(pose["x"], pose["y"]), image, False)
    assert fields["transform"] == ast.literal_eval(values["transform"])
    assert fields["footprint"] == ast.literal_eval(values["footprint"])
    assert world_file_text(fields["transform"]) == blocks[1]
    # The level affine's formulas as the page states them, computed here from A and B alone.
    w, h, b = pose["width"], pose["height"], complex(pose["x"], pose["y"])
    ta, tb, td, te = a.real, a.imag, a.imag, -a.real
    expected = [ta, tb, b.real - ta * w / 2 - tb * h / 2, td, te, b.imag - td * w / 2 - te * h / 2]
    assert fields["transform"] == pytest.approx(expected, abs=1e-4)


def test_world_file_names_and_the_sidecar() -> None:
    section = _section("World file and GDAL sidecar")
    rows = re.findall(r"^\| `([^`]+)` \| `([^`]+)` \|$", section, re.M)
    assert len(rows) >= 5
    for image, world in rows:
        assert world_file_name(image) == world
    transform = [0.5, 0.1, 100.0, 0.2, -0.5, 200.0]
    document = ET.fromstring(aux_xml_text("EPSG:32631", transform))
    # "<GeoTransform>c, a, b, f, d, e</GeoTransform>", as documented.
    order = re.search(r"<GeoTransform>([a-f, ]+)</GeoTransform>", section).group(1).split(", ")  # type: ignore[union-attr]
    named = dict(zip("abcdef", transform, strict=True))
    assert [float(v) for v in document.findtext("GeoTransform").split(",")] == [named[k] for k in order]
    assert document.find("SRS").get("dataAxisToSRSAxisMapping") == "1,2"


def test_the_documented_properties(answer) -> None:
    section = _section("GeoJSON layers")
    properties_text = section[section.index("Properties"):section.index("Lists and")]
    not_text = section[section.index("Lists and"):section.index("Rejected answers")]
    documented = set(re.findall(r"`([a-z_]+)`", properties_text))
    excluded = set(re.findall(r"`([a-z_]+)`", not_text))
    properties = set(answer.properties())
    assert properties <= documented and not properties & excluded
    assert excluded <= set(answer.to_json()) | {"skipped_labels"}
