"""The allocator policy: inside ``reuse_large_blocks`` a large temporary freed and allocated
again costs no new page faults; outside, glibc maps fresh pages every time."""

from __future__ import annotations

import resource
import sys

import pytest
import torch

from pbrsr_core.hostmem import _libc, reuse_large_blocks

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or _libc() is None, reason="glibc only"
)


def _faults_of_temporaries(n: int = 6) -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        t = torch.zeros(2048, 2048, 4)  # 64 MiB, freed at the end of each iteration
        del t
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def test_reused_blocks_do_not_fault_again():
    pages = 2048 * 2048 * 4 * 4 // 4096
    outside = _faults_of_temporaries()
    with reuse_large_blocks():
        _faults_of_temporaries(12)  # the first ones grow the heap
        inside = _faults_of_temporaries()
    after = _faults_of_temporaries()
    assert outside >= 3 * pages  # fresh pages every time
    assert inside < pages  # the same heap memory again
    assert after >= 3 * pages  # defaults restored on exit
