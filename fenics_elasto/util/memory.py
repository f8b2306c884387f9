"""Freed memory kept in the process, for the next big block to reuse.

An estimate allocates and frees blocks of a few hundred MB again and again: the mode
fields and their products (116k DOFs x 241 columns is 224 MB), their refinement's
residuals, MUMPS's solve workspace, the degree-3 matrix of sigma's mesh part. glibc
hands every block over 32 MB straight back to the kernel (mmap, then munmap), so the
next one is faulted in page by page again. Faults are not free: on this project's
2-core machine (a Firecracker VM whose free pages go back to the host) a 4 kB fault on
memory new to the process cost 2 us, and 20 us where the host had taken the page back;
and a rank-80 estimate of the default phantom spent 35 s of its 89 s in the
kernel, 2.2 million faults (8.9 GB touched fresh) for a peak of 6.1 GB.

Kept in the heap (no mmap for big blocks, no trimming of the heap's top), a freed block
is reused without a fault: the same estimate faults 1.3 million times, every page about
once, and took 70 s against 79-83 s; at rank 240 154 s against 185 s, E the same to the
bit (docs: performance). The price is that the process keeps its peak: memory freed late
in a run is not handed back until it ends (the estimate's peak 6.4 GB against 6.1 GB).
Set FENICS_ELASTO_RETAIN_MEMORY=0 to keep glibc's defaults (a long-lived process that does
other work after an estimate). Other C libraries (macOS, musl) have no mallopt: nothing
is set there.
"""

from __future__ import annotations

import ctypes
import os

SWITCH = "FENICS_ELASTO_RETAIN_MEMORY"
# mallopt's parameters (glibc's malloc.h)
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4
TOP_PAD = 256 << 20  # the heap grows in steps of at least this: fewer brk calls for big blocks


def retain_freed_memory() -> bool:
    """Tell glibc's malloc to keep freed memory for reuse; True if it was told."""
    if os.environ.get(SWITCH, "1") == "0":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # -1 turns trimming off altogether (man mallopt); mmap stays glibc's fallback where the
    # heap cannot grow (threads' arenas).
    return all(mallopt(param, value) == 1 for param, value in
               ((M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, -1), (M_TOP_PAD, TOP_PAD)))
