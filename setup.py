"""Build of mapdb's compiled kernel (``mapdb/match/_kernel*.c``); the metadata is in pyproject.toml.

The kernel is plain C on the CPython API: a C compiler and Python's headers build it (on Debian ``gcc`` and
``python3-dev``), with no numpy headers, Cython or other build dependency.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "mapdb.match._kernel",
            # One module from several files, a concept each (see _kernel.h).
            sources=["mapdb/match/_kernel.c", "mapdb/match/_kernel_buffers.c", "mapdb/match/_kernel_numpy.c",
                     "mapdb/match/_kernel_nfa.c",
                     "mapdb/match/_kernel_objects.c",
                     "mapdb/match/_kernel_object_discs.c",
                     "mapdb/match/_kernel_verify.c",
                     "mapdb/match/_kernel_verify_refine.c", "mapdb/match/_kernel_places.c",
                     "mapdb/match/_kernel_quads.c",
                     "mapdb/match/_kernel_quad_tree.c",
                     "mapdb/match/_kernel_image_quads.c",
                     "mapdb/match/_kernel_map_quads.c",
                     "mapdb/match/_kernel_stored.c", "mapdb/match/_kernel_stored_resolve.c",
                     "mapdb/match/_kernel_qdecode.c", "mapdb/match/_kernel_qcheck.c",
                     "mapdb/match/_kernel_screen.c",
                     "mapdb/match/_kernel_hits.c"],
            depends=["mapdb/match/_kernel.h", "mapdb/match/_kernel_objects.h", "mapdb/match/_kernel_quads.h",
                     "mapdb/match/_kernel_stored.h"],
            # No fused multiply-adds: the kernel's sums and products round as numpy's do.
            extra_compile_args=["-O2", "-ffp-contract=off"],
        )
    ]
)
