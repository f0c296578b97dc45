"""Page faults of a payload-buffer churn with and without ``runtime.tune_allocator``, in one run.

A burst of 40 buffers of ~100 KB is allocated and freed together, ten times, as a drained
receive queue does. The reference is the same churn in the same interpreter before tuning
(glibc's defaults). The target is at most a quarter of the reference's minor page faults
(``tests/comms/test_runtime.py`` had it as a unit-test threshold; a count that depends on the
machine's allocator belongs here).

    python benchmarks/allocator.py --json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys

TARGET_RATIO = 0.25

CHURN = """
import json, resource
from kimera_multi_py.comms import runtime
def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    keep = []
    for i in range(400):
        keep.append(bytes(100 * 1024 + i))   # a burst of payloads alive at once
        if len(keep) == 40:
            keep.clear()                      # ... freed together, as a drained queue is
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults()                      # warm up
untuned = faults()
tuned_ok = runtime.tune_allocator()
faults()
print(json.dumps({"untuned": untuned, "tuned": faults(), "tuned_ok": tuned_ok}))
"""


def measure() -> dict[str, object]:
    """Run the churn in a fresh interpreter (the allocator's state is per process)."""
    out = subprocess.run([sys.executable, "-c", CHURN], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "KMP_MALLOC_TUNE": "1"}, check=True)
    return json.loads(out.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON only")
    args = ap.parse_args()
    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    result: dict[str, object] = {"glibc": glibc, "target_ratio": TARGET_RATIO}
    if glibc:
        m = measure()
        untuned, tuned = int(m["untuned"]), int(m["tuned"])  # type: ignore[call-overload]
        ratio = tuned / max(untuned, 1)
        result.update(reference_minor_faults=untuned, tuned_minor_faults=tuned, ratio=round(ratio, 4),
                      tuned=m["tuned_ok"], meets_target=ratio <= TARGET_RATIO)
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
