"""Answer a batch of image documents in input order; a document that failed to decode is rejected on its own.

:func:`localize_documents` answers every document of a JSON Lines file (``mapdb query``), so that one bad
line never stops a batch.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from typing import Any

from ..answers import Answer
from ..match.fast import FastOptions
from ..match.paper.options import PaperOptions
from .localizer import localizer_for
from .records import rejected

__all__ = ["localize_documents"]


def localize_documents(
    documents: Iterable[tuple[str, Any]],
    map: Any,
    method: str = "fast",
    prior: tuple[float, float, float] | None = None,
    *,
    options: FastOptions | PaperOptions | None = None,
) -> Iterator[Answer]:
    """Answer every document of a batch, in order; a document that failed to decode is rejected.

    Parameters
    ----------
    documents : iterable of (where, document or ImageInputError)
        As :func:`mapdb.detections.images.split_image_documents` or
        :func:`~mapdb.detections.images.read_image_documents` give them.
    map, method, prior, options
        As for :func:`~mapdb.localize.localizer.localize`.

    Yields
    ------
    Answer
        One answer per document, as soon as that document is read (a lazy ``documents``, such as
        :func:`~mapdb.detections.images.read_image_documents` gives, is consumed one document at a time).  A
        rejection of a document without an ``id`` names its place (``where``) in the reason, so that
        it can be found in the input.
    """
    localizer = localizer_for(map, method, options)
    for where, doc in documents:
        if isinstance(doc, Exception):
            start = time.perf_counter()
            yield rejected(None, str(doc), start)
            continue
        answer = localizer.localize(doc, prior, source=where)
        if not answer.ok and answer.id is None and not (answer.reason or "").startswith(where):
            answer.reason = f"{where}: {answer.reason}"
        yield answer
