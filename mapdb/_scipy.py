"""The few scipy pieces the matcher uses, loaded without scipy's package-wide imports.

A one-image ``mapdb query`` is mostly process start-up, and most of that was importing scipy: ``from
scipy.spatial import cKDTree`` runs ``scipy/spatial/__init__.py``, which loads ``scipy.sparse``,
``scipy.linalg``, qhull, ``scipy.special`` and ``scipy.spatial.transform`` (about 0.3 s on the 2-core
benchmark machine), and ``scipy.special``'s package pulls scipy's array-API layer, which imports
``numpy.f2py`` and ``numpy.testing`` (another 0.13 s).  The matcher needs none of that: the compiled KD-tree
(``scipy.spatial._ckdtree``), the incomplete beta ufunc (``scipy.special._ufuncs``) and, only when an
answer's final association has rivals (about 1 answer in 100), ``scipy.sparse`` and the bipartite matching
of ``scipy.sparse.csgraph._matching``.

:data:`cKDTree` and :data:`betainc` are scipy's own objects (the same class and ufunc that
``scipy.spatial.cKDTree`` and ``scipy.special.betainc`` are; results are identical), loaded by
:func:`load_quietly`.  A later ``import scipy.spatial`` or ``scipy.special`` elsewhere works as usual and
reuses the modules loaded here.  If anything is unexpected (another scipy layout, a frozen application,
an import error), the normal import is used instead: slower to start, never different.

:func:`csr_array` and :func:`min_weight_full_bipartite_matching` import ``scipy.sparse`` on their first
call (0.1 s), the latter its own module quietly (not ``scipy.sparse.csgraph``'s package, which imports
``scipy.linalg`` and ``scipy.sparse.linalg``: 0.07 s more).
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
import threading
import types
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

__all__ = ["COPY_IF_NEEDED", "StandIn", "betainc", "cKDTree", "csr_array", "load_quietly",
           "min_weight_full_bipartite_matching", "quick_tree"]

_LOCK = threading.RLock()


def load_quietly(name: str, stand_ins: Mapping[str, Mapping[str, object]] | None = None) -> bool:
    """Load the module ``NAME`` (``package.sub.module``) without running ``package/sub/__init__.py``.

    While it loads, ``package.sub`` is a bare package in ``sys.modules`` (its ``__path__`` only, so the
    module's siblings load normally and its package's ``__init__`` does not run), and each module of
    ``stand_ins`` not yet imported is a :class:`StandIn` holding only the attributes given, for imports the
    module makes at load time but needs only in functions ours never call (``scipy.spatial._ckdtree``
    imports ``scipy.sparse`` for ``sparse_distance_matrix``, and looks it up as ``scipy.sparse`` when
    called, so it then finds the real one) or for a constant it takes (see :data:`COPY_IF_NEEDED`).  A name
    the module wants that a stand-in lacks fails the quiet load.  Afterwards neither the bare package nor a
    stand-in is left in ``sys.modules``; the modules loaded are.  The quiet load fails too when a module it
    loaded keeps a stand-in among its globals; the package's modules it loaded are then dropped from
    ``sys.modules`` for the normal import to load afresh (a compiled module that cannot be loaded twice
    keeps its stand-in, which then hands out the real module's attributes).

    Quiet loads wait for each other (a lock), but an import of ``package.sub`` or of a stand-in by another
    thread during the millisecond or so of a load could receive the bare package or the stand-in: mapdb
    loads the KD-tree and the beta function when ``mapdb.match`` is first imported, and the bipartite
    matching (:data:`min_weight_full_bipartite_matching`) on its first call.

    Returns
    -------
    bool
        True when ``NAME`` is in ``sys.modules`` afterwards (loaded here or before); False when the quiet
        load was not possible or went wrong, everything it added is taken back, and the caller's normal
        import does the work.

    Examples
    --------
    >>> load_quietly("scipy.spatial._ckdtree")  # already loaded when this module was imported
    True
    """
    with _LOCK:
        return _load_quietly(name, stand_ins or {})


def _load_quietly(name: str, stand_ins: Mapping[str, Mapping[str, object]]) -> bool:
    if name in sys.modules:
        return True
    package_name = name.rpartition(".")[0]
    top_name = package_name.rpartition(".")[0]
    if not top_name or package_name in sys.modules:
        return False  # nothing to save: the package is imported already (or NAME is not two levels deep)
    try:
        top = importlib.import_module(top_name)
        spec = importlib.machinery.PathFinder.find_spec(package_name, list(getattr(top, "__path__", [])))
    except Exception:  # noqa: BLE001 - whatever went wrong, the normal import decides
        return False
    if spec is None or spec.submodule_search_locations is None:
        return False  # not a plain package on the file system (a frozen application): the normal way
    added = {package_name: importlib.util.module_from_spec(spec)}
    for stand_in, attributes in stand_ins.items():
        if stand_in not in sys.modules:
            added[stand_in] = StandIn(stand_in)
            vars(added[stand_in]).update(attributes)
    before = set(sys.modules)
    sys.modules.update(added)
    try:
        module = importlib.import_module(name)
        ok = _untouched_by(added.values(), [sys.modules[m] for m in set(sys.modules) - before - set(added)])
    except Exception:  # noqa: BLE001 - an import error here only means: import it the normal way
        module, ok = None, False
    finally:
        for key, value in added.items():
            if sys.modules.get(key) is value:
                del sys.modules[key]
            parent, _, attr = key.rpartition(".")
            if getattr(sys.modules.get(parent), "__dict__", {}).get(attr) is value:
                delattr(sys.modules[parent], attr)
    if not ok:
        # Whatever loaded against the stand-ins may hold them: the normal import starts afresh.
        for key in set(sys.modules) - before:
            if key.startswith(package_name + ".") or not _untouched_by(added.values(), [sys.modules[key]]):
                del sys.modules[key]
    return ok and module is not None


class StandIn(types.ModuleType):
    """A module standing in for a real one during :func:`load_quietly`: it holds the attributes it is given;
    once out of ``sys.modules`` it hands out the real module's other attributes (importing it)."""

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("__") or sys.modules.get(self.__name__) is self:
            raise AttributeError(f"stand-in for {self.__name__} has no attribute {attr!r}")
        return getattr(importlib.import_module(self.__name__), attr)


def _untouched_by(stand_ins: Any, modules: list[Any]) -> bool:
    """No module of ``modules`` keeps one of ``stand_ins`` among its globals."""
    ids = {id(s) for s in stand_ins}
    return not any(id(value) in ids for m in modules for value in list(getattr(m, "__dict__", {}).values()))


def _on_first_call(module: str, name: str, *, quiet: bool = False) -> Callable[..., Any]:
    """``module.name``, imported when first called.  With ``quiet``, ``module`` is loaded by
    :func:`load_quietly`, and if that cannot be, ``name`` is taken from its package the normal way."""
    found: list[Callable[..., Any]] = []

    def call(*args: Any, **kwargs: Any) -> Any:
        if not found:
            with _LOCK:  # two threads' first calls: one loads, the other waits (and sees no bare package)
                if not found:
                    home = module if not quiet or load_quietly(module) else module.rpartition(".")[0]
                    found.append(getattr(importlib.import_module(home), name))
        return found[0](*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"``{module}.{name}``, imported on first call."
    return call


# numpy's "copy only if needed" for ``np.array(..., copy=)``: None since numpy 2, False before.  scipy's
# ``scipy._lib._util.copy_if_needed`` is this, and it is all ``_ckdtree`` takes from that module, whose
# import costs 0.13 s (scipy's array-API layer, which imports numpy.f2py and numpy.testing).
COPY_IF_NEEDED = None if int(np.__version__.split(".")[0]) >= 2 else False

load_quietly("scipy.spatial._ckdtree",
             stand_ins={"scipy.sparse": {}, "scipy._lib._util": {"copy_if_needed": COPY_IF_NEEDED}})
load_quietly("scipy.special._ufuncs")

# With the modules in sys.modules these import nothing more; without (the quiet load not possible), they
# are the normal, slower imports of the same objects.
from scipy.spatial._ckdtree import cKDTree  # noqa: E402

try:
    from scipy.special._ufuncs import betainc  # noqa: E402
except ImportError:  # a scipy whose ufunc lives elsewhere
    from scipy.special import betainc  # noqa: E402


def quick_tree(points: np.ndarray) -> cKDTree:
    """A :class:`cKDTree` built with sliding midpoint splits and no node shrinking: about half the build
    time of the defaults, and queries as fast or faster (17 % faster on a 5M-object map's verification
    queries); a query's nearest neighbours do not depend on how the tree splits."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


csr_array = _on_first_call("scipy.sparse", "csr_array")
# scipy.sparse.csgraph's package imports scipy.linalg and scipy.sparse.linalg (0.07 s); its matching module
# needs neither.
min_weight_full_bipartite_matching = _on_first_call("scipy.sparse.csgraph._matching",
                                                    "min_weight_full_bipartite_matching", quiet=True)
