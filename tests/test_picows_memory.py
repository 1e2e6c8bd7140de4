"""A picows connection that once received a large message does not keep the memory of it.

``picows`` grows a connection's read buffer to hold a frame and never shrinks it; the picows
transport hands the pages it grew by back to the system once the frame is read. Measured as
the resident memory (``VmRSS``) of a process holding many idle connections that each received
one large message, against the same process after small messages only
(``benchmarks/picows_memory.py``, which runs the measured process on its own).
"""

from __future__ import annotations

import re

import pytest

from support import ROOT, run_benchmark

SCRIPT = ROOT / "benchmarks" / "picows_memory.py"
CONNECTIONS = 40
LARGE = 2**20


def rss_mib(*args: str) -> float:
    """The measured process's resident memory, as the benchmark reports it."""
    output = run_benchmark(SCRIPT, "--connections", str(CONNECTIONS), *args).stdout
    match = re.search(r"VmRSS ([0-9.]+) MiB", output)
    assert match, output
    return float(match.group(1))


@pytest.mark.parametrize("side", ["server", "client"])
def test_connections_give_back_the_read_buffer_a_large_message_grew(side: str) -> None:
    small = rss_mib("--transport", "picows", "--side", side, "--size", "100")
    large = rss_mib("--transport", "picows", "--side", side, "--size", str(LARGE))
    # Kept, each connection would hold its 1 MiB message's buffer: 40 MiB more in all.
    assert large - small < CONNECTIONS * LARGE / 2**20 / 4, (small, large)
