"""An OSM extract with a share of its buildings left out: the incomplete map a user's OSM data gives.

A flight rendered from the whole extract (:mod:`mapdb.navigation.rendered`) over a map built from the
thinned one (``mapdb build THINNED -o MAP``) sees buildings the map does not have, as a camera over a town
whose OSM buildings are only partly mapped does::

    from mapdb.simulation.thinning import thin_extract
    thin_extract("monaco.osm.pbf", "monaco-thin.osm.pbf", share=0.15, seed=1)

Each way or relation tagged ``building`` (any value but ``no``) is left out with probability ``share``,
decided by a hash of ``(seed, kind, id)`` alone, so that the same extract, share and seed always leave out
the same buildings, whatever else the file holds.  Everything else (nodes, other ways and relations) is
copied as it is; a building relation left out leaves its member ways in place, untagged ones drawing
nothing.  A building mapped as a node is kept (it has no outline to render).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

from ..errors import SourceError

__all__ = ["is_left_out", "thin_extract"]


def is_left_out(kind: str, osm_id: int, share: float, seed: int) -> bool:
    """Whether the building ``kind`` (``"w"`` or ``"r"``) ``osm_id`` is left out (module docs).

    Examples
    --------
    >>> is_left_out("w", 12, 0.0, 1), is_left_out("w", 12, 1.0, 1)
    (False, True)
    >>> sum(is_left_out("w", i, 0.15, 3) for i in range(10_000))  # about 1,500
    1570
    """
    digest = hashlib.blake2b(f"{seed}:{kind}:{osm_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2.0**64 < share


def thin_extract(source: str | Path, output: str | Path, share: float, seed: int = 0) -> dict[str, int]:
    """Copy ``source`` to ``output`` (an OSM file; its suffix picks the format) without a ``share`` of its
    buildings (module docs).

    Returns
    -------
    dict
        ``{"buildings": kept + left out, "left_out": ...}``.

    Raises
    ------
    ValueError
        ``share`` outside [0, 1].
    SourceError
        ``source`` is not a readable OSM file.
    """
    import osmium

    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ValueError(f"share must be in [0, 1], got {share}")
    counts = {"buildings": 0, "left_out": 0}
    output = Path(output)
    output.unlink(missing_ok=True)  # the writer refuses an existing file
    try:
        with osmium.SimpleWriter(str(output)) as writer:
            for obj in osmium.FileProcessor(str(source)):
                kind = obj.type_str()
                if kind in ("w", "r") and obj.tags.get("building", "no") != "no":
                    counts["buildings"] += 1
                    if is_left_out(kind, obj.id, share, seed):
                        counts["left_out"] += 1
                        continue
                writer.add(obj)
    except RuntimeError as exc:
        output.unlink(missing_ok=True)
        raise SourceError(f"{source}: not a readable OSM file ({exc})") from None
    return counts
