"""Freed memory kept for reuse (util/memory.py): a big block freed and allocated again
is not faulted in again once the package is imported, and is with the switch off. Each
case runs in a fresh interpreter: the setting is made when the package is imported."""

import json
import os
import subprocess
import sys

import pytest

MB = 200
# Touch a 200 MB block, free it, then count the minor page faults of touching a new one
# (a bytearray: numpy would ask for huge pages, which fault 512 pages at a time).
PROBE = f"""
import json, resource
import fenics_elasto
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = bytearray({MB} << 20); del a  # malloc, then zeroed: every page touched
before = faults(); b = bytearray({MB} << 20); after = faults()
print(json.dumps(after - before))
"""


def refaults(**env) -> int:
    clean = {k: v for k, v in os.environ.items() if k != "FENICS_ELASTO_RETAIN_MEMORY"}
    out = subprocess.run([sys.executable, "-c", PROBE], env=clean | env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")


def test_a_freed_block_is_reused_without_faults():
    """Kept: reused in place, almost no fault. glibc's default: handed back and faulted
    in again, a fault per 4 kB page (per 2 MB where the kernel backs every mapping with
    huge pages: still far more)."""
    kept = refaults()
    assert kept < 0.02 * (MB << 20) // 4096
    assert refaults(FENICS_ELASTO_RETAIN_MEMORY="0") > 20 * max(kept, 1)
