"""Process-wide tuning of glibc's allocator for the image-processing processes.

NumPy and OpenCV allocate and free many arrays of a few megabytes per image tile. With
glibc's defaults each such array is a fresh ``mmap`` whose pages fault in on first touch,
which measured at ~25 % of the detector's time; keeping them on the heap (and not
trimming it after every free) reuses warm pages instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 2**20  # glibc's upper bound for this option on 64-bit
TRIM_THRESHOLD_BYTES = 256 * 2**20


def keep_arrays_on_heap() -> bool:
    """Serve allocations below 32 MB from the heap and keep up to 256 MB of freed memory
    for reuse; False where the C library is not glibc (nothing changes)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    if not ok:
        log.debug("mallopt refused the allocator settings")
    return ok
