"""glibc's malloc told to give large freed buffers back: a fixed mmap threshold.

glibc serves a request of at least ``M_MMAP_THRESHOLD`` bytes (128 KiB at first) with a
mapping of its own, unmapped when freed. But every such free raises the threshold to the
freed size (up to 32 MiB on 64-bit), so afterwards the same temporary arrays (the submap's
union of points, a rebuilt grid, a shipped job) come from the heap instead, between the
small arrays that live for the whole run (keyframes): the heap only shrinks from its top,
and the daemon's resident memory keeps its highest level. Setting the threshold
explicitly turns that adjustment off (mallopt(3), "M_MMAP_THRESHOLD" and "M_TRIM_THRESHOLD").
Processes started afterwards (the fork server, the loop-closure worker, the control process)
read the same setting from ``MALLOC_MMAP_THRESHOLD_`` in their environment (mallopt(3),
"Environment variables"). On a C library other than glibc nothing changes.

Example::

    fix_mmap_threshold()    # True on glibc: this process and the ones it starts
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import MutableMapping

#: Requests of at least this many bytes get a mapping of their own, returned to the kernel when freed.
MMAP_THRESHOLD_BYTES = 128 * 1024
_M_MMAP_THRESHOLD = -3  # glibc's <malloc.h>
ENV_NAME = "MALLOC_MMAP_THRESHOLD_"


def fix_mmap_threshold(environ: MutableMapping[str, str] | None = None) -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD_BYTES` here and in processes started later.

    A threshold already set in the environment (by the unit, by the user) is left as it is.
    Returns whether this process's malloc took the setting (False off glibc).
    """
    env = os.environ if environ is None else environ
    value = env.setdefault(ENV_NAME, str(MMAP_THRESHOLD_BYTES))
    try:
        threshold = int(value)
        mallopt = ctypes.CDLL(None).mallopt
    except (ValueError, OSError, AttributeError):  # a bad value stays glibc's to judge; no glibc
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold))


def give_back_free_memory() -> bool:
    """Return the free pages inside malloc's heaps to the kernel (glibc's ``malloc_trim(0)``).

    Freed small blocks between live ones keep their pages resident until then: the heap
    only shrinks from its top on its own (malloc_trim(3)). About a millisecond for the
    daemon's heap; called after each loop-closure job, the one moment in seconds that frees a
    whole job's temporaries at once. Returns whether memory was given back (False off glibc).
    """
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes = (ctypes.c_size_t,)
    trim.restype = ctypes.c_int
    return bool(trim(0))
