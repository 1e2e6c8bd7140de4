"""keep_freed_heap: process-wide, so each check that changes the allocator runs in a fresh process.

The pattern measured is a large message's: three blocks of about 2 MB alive at once, then none,
again and again. glibc hands the top of its heap back after each round and faults it in again
in the next one; once freed heap is kept, the rounds after the first take no page faults.
"""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

import srvwire
from srvwire.heap import keep_freed_heap

ROUNDS = """
import resource, sys
from srvwire import keep_freed_heap

if sys.argv[1] == "keep":
    assert keep_freed_heap() is True

def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

def message():
    held = [b"x" * 2_000_000 for _ in range(3)]  # written, so every page is touched
    del held

for _ in range(3):  # the first rounds settle the allocator's own thresholds
    message()
before = faults()
for _ in range(10):
    message()
print(faults() - before)
"""

PAGES_A_ROUND = 3 * 2_000_000 // 4096


def faults_of(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", ROUNDS, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout)


glibc_only = pytest.mark.skipif(
    platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's: elsewhere nothing changes"
)


@glibc_only
def test_kept_heap_serves_large_messages_again_without_page_faults() -> None:
    assert faults_of("default") > 5 * PAGES_A_ROUND  # handed back and faulted in, round by round
    assert faults_of("keep") < PAGES_A_ROUND // 10  # kept: next to none, in ten rounds


def test_it_is_the_packages_own_and_refuses_a_size_the_c_library_cannot_take() -> None:
    assert srvwire.keep_freed_heap is keep_freed_heap
    for size in (-1, 0, 2**20 - 1, 2**31):
        with pytest.raises(ValueError, match="size must be between 1048576 and 2147483647 bytes"):
            keep_freed_heap(size)


def test_elsewhere_than_glibc_it_changes_nothing_and_says_so(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(platform, "libc_ver", lambda *args, **kwargs: ("musl", "1.2"))
    assert keep_freed_heap() is False
