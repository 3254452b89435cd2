"""needletissue: bone needles (Schanz pins) and pelvic soft tissue deforming together.

Units everywhere: mm, N, MPa (= N/mm^2), s; densities in t/mm^3 internally, g/cm^3 in tables.
"""

__version__ = "0.1.0"


def _one_malloc_arena():
    """Make every thread allocate from glibc's main heap. By default each thread that allocates gets its own
    heap ("arena"), and what the FE assembly threads freed there stays resident beside Pardiso's factor: one
    arena lowers the one-needle model's peak 524 -> 451 MB and the default `fe needle`'s ~0.95 -> 0.85 GB
    (docs/bench.md, "One heap for the assembly threads"). Process-wide, and set when the package is imported:
    a thread that allocated before (NumPy's, Numba's) has a heap of its own, and later threads would share it
    instead of the main one. Left alone if the user set MALLOC_ARENA_MAX; a no-op without glibc."""
    import ctypes
    import os

    if "MALLOC_ARENA_MAX" not in os.environ:
        try:
            ctypes.CDLL(None).mallopt(-8, 1)  # M_ARENA_MAX (malloc.h)
        except (AttributeError, OSError):
            pass


_one_malloc_arena()
