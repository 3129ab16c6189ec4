"""The allocator policy: inside ``reuse_large_blocks`` a large temporary freed and allocated
again costs no new page faults; outside, glibc maps fresh pages every time; on leaving, the
kept heap memory goes back to the system.

Measured in a child process with transparent huge pages turned off for it
(``prctl(PR_SET_THP_DISABLE)``): with THP a fresh 64 MiB block may fault once per 2 MiB page
instead of once per 4 KiB page, depending on the machine's memory state, and the counts below
would not mean what they say."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from pbrsr_core.allocator import _libc

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or _libc() is None, reason="glibc only"
)

SCRIPT = r"""
import ctypes, json, resource
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: 4 KiB pages for this process
import torch
from pbrsr_core.allocator import reuse_large_blocks

def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024

def faults(n=6):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        t = torch.zeros(2048, 2048, 4)  # 64 MiB, freed at the end of each iteration
        del t
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

outside = faults()
with reuse_large_blocks():
    faults(12)  # the first ones grow the heap
    inside = faults()
    kept = rss()
returned = kept - rss()
print(json.dumps({"outside": outside, "inside": inside, "returned_mib": returned / 2**20}))
"""


def test_reused_blocks_do_not_fault_again():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    pages = 2048 * 2048 * 4 * 4 // 4096
    assert r["outside"] >= 3 * pages, r  # fresh pages every time
    assert r["inside"] < pages, r  # the same heap memory again
    assert r["returned_mib"] >= 48, r  # the kept 64 MiB block is given back on exit
