"""The C library's allocator, set for services that run for hours (gateway, recorder).

glibc gives threads that allocate at the same time arenas of their own, up to
eight per core. A bodynet service has a dozen threads (Zenoh's runtime, the
Python callbacks it runs, the worker), and each arena keeps the memory freed
into it for its own later use: memory freed in one arena is not reused by
another. Two arenas kept the gateway's and the recorder's resident memory
about 2.5 MB lower after warm-up in the soak (glibc's own free space, as
``mallinfo2`` counts it: 3 MB against 6 MB), and flat; on two cores more
arenas buy little concurrency. docs/benchmarks.md, "Memory over an hour".
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform

#: Arenas a service's allocations are spread over.
ARENAS = 2
_M_ARENA_MAX = -8  # glibc's malloc.h


@functools.cache  # once per process
def limit_malloc_arenas(arenas: int = ARENAS) -> bool:
    """Cap glibc's malloc arenas at ``arenas`` for this process; True if done.

    Call it before the Zenoh session starts its threads (arenas made before
    stay). Left alone (False): a C library that is not glibc, or a user's own
    ``MALLOC_ARENA_MAX`` in the environment, which glibc has already applied."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_ARENA_MAX, arenas))
