"""An answer's camera image placed on the map for GIS tools: a world file and a GDAL ``.aux.xml`` beside it.

``mapdb georef ANSWERS.jsonl IMAGE`` writes, beside ``IMAGE``:

* the **world file** (ESRI's six lines, which GDAL, QGIS and ArcGIS read): ``A``, ``D``, ``B``, ``E``, ``C``,
  ``F``, each the shortest decimal that reads back as the same double, with ``x = A col + B row + C`` and
  ``y = D col + E row + F`` for the *centre* of pixel ``(col, row)`` (counted from 0), so ``C, F`` is the
  centre of the top-left pixel, half a pixel in from the answer's ``transform`` (whose origin is the
  top-left *corner*).  Its name follows the image's: the first and last letters of the extension and ``w``
  (``.png`` -> ``.pgw``, ``.tif`` -> ``.tfw``, ``.jpg`` -> ``.jgw``), ``.wld`` for an image without an
  extension of at least two letters.
* the **GDAL PAM sidecar** ``IMAGE.aux.xml``: the map's CRS (``<SRS>``, which a world file cannot hold) and
  the same transform (``<GeoTransform>``).  GDAL reads PAM before a GeoTIFF's own tags, so even a GeoTIFF
  that carries a georeference of its own is placed where the answer says.

For a tilted camera the transform is the best affine of the pinhole projection over the image
(:mod:`mapdb.localize.georef`): the image is then placed to within the answer's ``transform_error_m``.

Examples
--------
>>> world_file_name("flight/frame-0001.png"), world_file_name("chip.tif"), world_file_name("raw")
('flight/frame-0001.pgw', 'chip.tfw', 'raw.wld')
>>> print(world_file_text((0.5, 0.0, 840.0, 0.0, -0.5, 2120.0)), end="")
0.5
0.0
0.0
-0.5
840.25
2119.75
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from xml.sax.saxutils import escape

from ..answers import Answer
from ..errors import ImageInputError

__all__ = ["aux_xml_name", "aux_xml_text", "checked_answer", "world_file_name", "world_file_text"]


def world_file_name(image: str | os.PathLike[str]) -> str:
    """The world file GDAL looks for beside ``image`` (module docs)."""
    root, ext = os.path.splitext(os.fspath(image))
    letters = ext[1:]
    if len(letters) < 2:
        return os.fspath(image) + ".wld" if letters else root + ".wld"
    return f"{root}.{letters[0]}{letters[-1]}w"


def aux_xml_name(image: str | os.PathLike[str]) -> str:
    """GDAL's PAM sidecar of ``image``: its full name and ``.aux.xml``."""
    return os.fspath(image) + ".aux.xml"


def world_file_text(transform: Sequence[float]) -> str:
    """The six lines of a world file for a pixel-corner affine ``(a, b, c, d, e, f)`` (module docs)."""
    a, b, c, d, e, f = (float(t) for t in transform)
    centre_x, centre_y = c + 0.5 * a + 0.5 * b, f + 0.5 * d + 0.5 * e
    # The shortest text that reads back as the same double: no digits of float noise, nothing lost.
    return "".join(f"{value!r}\n" for value in (a, d, b, e, centre_x, centre_y))


def aux_xml_text(crs: str, transform: Sequence[float]) -> str:
    """A GDAL PAM document holding the CRS (as WKT) and the affine in GDAL's order ``c, a, b, f, d, e``."""
    from pyproj import CRS

    a, b, c, d, e, f = (float(t) for t in transform)
    wkt = CRS.from_user_input(crs).to_wkt()
    # x is the first axis whatever the CRS's own order says (GDAL's traditional GIS order).
    return ("<PAMDataset>\n"
            f'  <SRS dataAxisToSRSAxisMapping="1,2">{escape(wkt)}</SRS>\n'
            f"  <GeoTransform>{c!r}, {a!r}, {b!r}, {f!r}, {d!r}, {e!r}</GeoTransform>\n"
            "</PAMDataset>\n")


def _numbers(values: object, n: int) -> bool:
    """Whether ``values`` is a list of ``n`` finite numbers (a hand-edited answer may hold anything)."""
    return (isinstance(values, list) and len(values) == n
            and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in values))


def checked_answer(answers: Sequence[Answer], image_id: str | None, source: str, image: str,
                   size: tuple[int, int]) -> Answer:
    """The answer that places ``image`` (of ``size`` width, height pixels), or a one-line
    :class:`~mapdb.errors.ImageInputError`.

    ``image_id`` picks the answer by its ``id``; without it ``source`` must hold exactly one accepted answer.
    The answer must be accepted, carry a ``transform`` and a CRS, and be of an image of the same size.
    """
    if image_id is None:
        ok = [a for a in answers if a.ok]
        if len(ok) != 1:
            raise ImageInputError(f"{source}: {len(ok)} accepted answers; choose one with --id")
        answer = ok[0]
    else:
        chosen = [a for a in answers if str(a.id) == image_id]
        if not chosen:
            raise ImageInputError(f"{source}: no answer with id {image_id!r}")
        answer = chosen[0]
    name = f"answer {answer.id!r}"
    if not answer.ok:
        raise ImageInputError(f"{source}: {name} is not accepted ({answer.reason}): nothing to place")
    if not _numbers(answer.transform, 6) or not _numbers([answer.width, answer.height], 2):
        raise ImageInputError(f"{source}: {name} has no transform (written by an older mapdb, or the image "
                              f"reaches the horizon): query again")
    if not isinstance(answer.crs, str) or not answer.crs:
        raise ImageInputError(f"{source}: {name} has no CRS (its map has none): a GIS cannot place it")
    if (float(size[0]), float(size[1])) != (answer.width, answer.height):
        raise ImageInputError(f"{image}: the image is {size[0]}x{size[1]} pixels but {name} in {source} is of a "
                              f"{answer.width:g}x{answer.height:g} image")
    return answer
