"""Keep freed CPU memory for reuse: the allocator setting the package's own training processes run with.

A CPU training step allocates and frees the same large tensors every step (the tiny models' 32^3 volumes are
12.6 MB each). With glibc's defaults the freed top of the heap goes back to the operating system as soon as
more than a few tens of megabytes are free, so the next step takes every page of it again as a page fault.
:func:`retain_freed_memory` tells glibc to keep up to 256 MiB of freed memory and to serve tensors up
to 32 MiB from it, the way PyTorch's CUDA allocator keeps GPU memory. The ``lightning-vtr`` command and the experiment runners (the examples, ``lightning-vtr report``)
call it; a script that trains with its own ``Trainer`` can call it once at its start.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

__all__ = ["retain_freed_memory"]

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Free memory glibc keeps at the top of the heap before returning it (its default adapts up to 64 MiB).
TRIM_THRESHOLD = 256 * 2**20
#: Allocations from this size up get their own mapping, returned when freed (glibc's largest; default adapts).
MMAP_THRESHOLD = 32 * 2**20
#: Environment variables by which a user sets glibc's allocator; when one is set, it is left as the user chose.
USER_SETTINGS = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")


def retain_freed_memory() -> bool:
    """Have glibc keep freed memory for reuse in this process; ``True`` if it now does.

    Sets glibc's trim threshold to :data:`TRIM_THRESHOLD` and its mmap threshold to :data:`MMAP_THRESHOLD`
    (``mallopt``). The process's resident memory then stays near its peak instead of shrinking between
    steps. Does nothing and returns ``False`` off Linux, with another C library, or when the environment sets
    glibc's allocator itself (one of :data:`USER_SETTINGS`). Calling it again changes nothing.

    Example:
        Once, at the start of a script that trains on the CPU with its own ``Trainer``::

            from lightning_vtr.utils.memory import retain_freed_memory

            retain_freed_memory()
    """
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    if any(name in os.environ for name in USER_SETTINGS):
        return False
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is None:  # pragma: no cover - every glibc has it
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success; both are needed (either one alone turns glibc's adaptive thresholds off).
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
