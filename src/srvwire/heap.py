"""Keep freed heap memory for reuse: a process-wide choice for peers of large messages.

glibc's ``malloc`` hands the top of its heap back to the kernel whenever more than a threshold
of it is free, and a process that then needs it again takes a page fault for every 4 KiB it
touches. A peer that sends or reads a multi-megabyte message per call frees everything that
message took when the call ends, so it pays those faults again for every message (about 1 000
a reply on the W4 benchmark: a fifth to a quarter of a side's CPU per call). How much is free
at once decides it, which srvwire keeps as small as it can (a reply is written and read whole,
in one pass), but pydantic-core's own working memory for a large JSON array is more than the
threshold on its own.

:func:`keep_freed_heap` asks the C library to keep freed memory instead; nothing in srvwire
calls it, since it changes the allocator of the whole process: an application that serves or
reads large messages calls it once, at start. It sets two of ``mallopt``'s parameters, as the
environment variables ``MALLOC_TRIM_THRESHOLD_`` and ``MALLOC_MMAP_THRESHOLD_`` would when the
process starts: the trim threshold (how much free heap is kept) and the mmap threshold (blocks
smaller than it come from the heap rather than from a mapping of their own, which is handed
back as soon as it is freed). Either alone is not enough: a process whose heap is small maps
every large block by itself, and setting one turns off glibc's own adjustment of the other.
"""

from __future__ import annotations

import platform

__all__ = ["DEFAULT_KEPT_HEAP", "MIN_KEPT_HEAP", "keep_freed_heap"]

DEFAULT_KEPT_HEAP = 64 * 2**20
"""What :func:`keep_freed_heap` keeps by default: 64 MiB of freed heap."""
MIN_KEPT_HEAP = 2**20
"""The least :func:`keep_freed_heap` takes: 1 MiB. Below it the thresholds would be lower than
glibc's own (an mmap threshold of 0 maps every block by itself, several times slower)."""

_M_TRIM_THRESHOLD = -1  # glibc's <malloc.h>
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_MAX = 32 * 2**20  # the most glibc takes on a 64-bit machine
_INT_MAX = 2**31 - 1


def keep_freed_heap(size: int = DEFAULT_KEPT_HEAP) -> bool:
    """Ask glibc's ``malloc`` to keep up to ``size`` bytes of freed heap; return whether it could.

    Process-wide and lasting: memory freed at the top of the heap stays with the process, up
    to ``size`` bytes beyond what is in use, and is reused without page faults, so the resident
    memory stays at its high-water mark rather than shrinking after each large message; and a
    block smaller than ``size`` (at most 32 MiB) comes from the heap, so it is kept too.
    ``size`` must be more than what the process frees at once (a message and every copy made
    of it, several times the message): smaller, the freed memory is still handed back, and
    since this turns off glibc's own adjustment of its thresholds, a process can then take more
    page faults than without the call. Returns False, and changes nothing, where the C library
    is not glibc (musl, macOS, Windows). Raises ``ValueError`` for a size below
    :data:`MIN_KEPT_HEAP` or one that does not fit a C ``int``.
    """
    if not MIN_KEPT_HEAP <= size <= _INT_MAX:
        raise ValueError(f"size must be between {MIN_KEPT_HEAP} and {_INT_MAX} bytes, not {size!r}")
    if platform.libc_ver()[0] != "glibc":
        return False
    import ctypes  # here, not at the top: srvwire imports without it

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    threshold = min(size, _MMAP_THRESHOLD_MAX)
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, size))
