"""Check that a refactoring changed no result: team-run metrics and distributed-PGO rounds
against the figures stored in ``tests/data/identical/`` (measured before the package split).

    python tests/check_identical.py            # sims + PGO benchmark (needs the g2o datasets)
    python tests/check_identical.py --no-pgo   # sims only
    python tests/check_identical.py --write    # store the current figures as the new reference

Compared: every non-timing field of ``Results.metrics()`` for ``sims/tiny.toml`` and
``sims/small.toml``, seed 0, distributed and centralised; and for every run of
``benchmarks/pgo.py --json`` its rounds, rounds to 1e-2 and 1e-3, and both costs.
Exit code 0 when all agree, 1 with the differing fields listed otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DATA = REPO / "tests" / "data" / "identical"
RUNS = [("tiny", "distributed"), ("tiny", "centralized"), ("small", "distributed"), ("small", "centralized")]
PGO_KEYS = ("rounds", "rounds_to_1e-2", "rounds_to_1e-3", "distributed_cost", "centralized_cost")


def sim_metrics() -> dict[str, Any]:
    from kimera_multi_py.sim.scenario import load_scenario
    from kimera_multi_py.workflow.simulate import SimRunner

    out = {}
    for scenario, mode in RUNS:
        cfg = load_scenario(REPO / "sims" / f"{scenario}.toml")
        out[f"{scenario}/{mode}"] = SimRunner(cfg, seed=0, mode=mode).run().metrics()
        print(f"ran {scenario} {mode}", file=sys.stderr, flush=True)
    return out


def pgo_rounds() -> list[dict[str, Any]]:
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "pgo.py"), "--json"], capture_output=True,
                          text=True, check=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    rows = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    return [{k: r[k] for k in ("dataset", "robots", "robust", *PGO_KEYS)} for r in rows]


def differences(want: Any, got: Any, path: str = "") -> list[str]:
    if isinstance(want, dict) and isinstance(got, dict):
        out = [f"{path}/{k}: only in the reference" for k in want.keys() - got.keys()]
        out += [f"{path}/{k}: only now" for k in got.keys() - want.keys()]
        for k in want.keys() & got.keys():
            out += differences(want[k], got[k], f"{path}/{k}")
        return out
    if isinstance(want, list) and isinstance(got, list) and len(want) == len(got):
        return [d for i, (w, g) in enumerate(zip(want, got, strict=True)) for d in differences(w, g, f"{path}[{i}]")]
    return [] if want == got else [f"{path}: {want!r} then, {got!r} now"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="store the current figures as the reference")
    ap.add_argument("--no-pgo", action="store_true", help="skip the PGO benchmark")
    args = ap.parse_args()
    found: list[str] = []
    parts = [("metrics.json", sim_metrics)] + ([] if args.no_pgo else [("pgo_rounds.json", pgo_rounds)])
    for name, measure in parts:
        got = measure()
        if args.write:
            (DATA / name).write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
            continue
        diff = differences(json.loads((DATA / name).read_text()), json.loads(json.dumps(got)), name)
        print(f"{name}: {'identical' if not diff else f'{len(diff)} differences'}")
        found += diff
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
