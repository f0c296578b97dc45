"""Distributed PGO vs the centralised gtsam reference on every graph in shared/datasets/pgo.

    python benchmarks/pgo.py --json            # six datasets, 5 robots, default cap, plus the
                                               # robust run and the team-size sweep
    python benchmarks/pgo.py --only sphere2500 --robots 5 --no-teams

Prints one JSON object per run (with ``--json``) and a table; the centralised reference
(chordal + LM, or gtsam's GNC for a robust run) is measured in the same process; robust runs
report both solutions' TLS cost (``tls_gap``) and the Jaccard index of their inlier sets. Rounds and bytes are
reported together: ``bytes_per_round`` is the team's bytes on the wire divided by the rounds run,
``bytes_to_1e-3`` the bytes sent until the gap first reached 1e-3 (rounds_to_1e-3 rounds).
``--teams`` also runs sphere2500 and torus3D with 10 and 20 robots; ``--robust-all`` adds a robust
run on every dataset, outliers unknown (scored without ground truth).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kimera_multi_py.cli.pgo import CLI_METHOD  # noqa: E402
from kimera_multi_py.pgo.params import PgoParams  # noqa: E402
from kimera_multi_py.workflow.pgo_benchmark import run_pgo  # noqa: E402

DATASETS = ("tinyGrid3D", "smallGrid3D", "sphere2500", "parking-garage", "torus3D", "cubicle")
# 2-D graphs (mit-acl/dpgo ``data/``, sources and licences in docs/benchmarks.md), run when their
# file is in the data folder: the reference starts chordal as in 3-D and says when it failed
OPTIONAL = ("input_INTEL_g2o", "input_M3500_g2o", "kitti_00", "CSAIL")
ROBUST = ("smallGrid3D", 0.5)
TEAMS = (("sphere2500", 10), ("sphere2500", 20), ("torus3D", 10), ("torus3D", 20))
DEFAULT_DIR = Path(os.environ.get("KMP_DATASETS", REPO.parent / "shared" / "datasets")) / "pgo"


def _params(args: argparse.Namespace) -> PgoParams:
    params = PgoParams(acceleration=args.acceleration, method=args.method or CLI_METHOD)
    if args.over_relaxation is not None:
        params.over_relaxation = args.over_relaxation
    params.distributed_init = args.distributed_init
    if args.rel_tol is not None:
        params.rel_tol = args.rel_tol
    return params


def _figures(res: Any) -> dict[str, Any]:
    """The run's JSON plus rounds and bytes side by side."""
    fig = res.to_json()
    rounds = max(int(fig["rounds"]), 1)
    fig["bytes_per_round"] = fig["bytes_sent"] / rounds
    r3 = fig["rounds_to_1e-3"]
    fig["bytes_to_1e-3"] = None if r3 is None else round(fig["bytes_per_round"] * (r3 + 1))
    fig.pop("inlier_sets", None)  # edge lists: in results.json, not in the benchmark lines
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object per run")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--max-rounds", type=int, default=500, help="round cap (the CLI's default)")
    ap.add_argument("--only", nargs="*", default=None, help="dataset names to run")
    ap.add_argument("--no-robust", action="store_true")
    ap.add_argument("--no-teams", action="store_true", help="skip the 10/20-robot sweep")
    ap.add_argument("--robust-dataset", default=ROBUST[0])
    ap.add_argument("--robust-all", action="store_true",
                    help="also a robust run (no injected outliers, truth unknown) on every dataset")
    ap.add_argument("--outliers", type=float, default=ROBUST[1])
    ap.add_argument("--data", type=Path, default=DEFAULT_DIR)
    ap.add_argument("--rel-tol", type=float, default=None, help="ready tolerance override")
    ap.add_argument("--acceleration", action="store_true",
                    help="Nesterov momentum instead of the default adaptive block SOR")
    ap.add_argument("--over-relaxation", type=float, default=None,
                    help="fixed SOR factor (1.0: plain Gauss-Seidel; default adaptive)")
    ap.add_argument("--method", choices=("block_sor", "gn_pcg"), default=None,
                    help="distributed solver (default: the CLI's, cli_pgo.CLI_METHOD)")
    ap.add_argument("--distributed-init", action="store_true",
                    help="chordal block Gauss-Seidel initialisation before the BCD")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)

    names = args.only or DATASETS + tuple(n for n in OPTIONAL if (args.data / f"{n}.g2o").exists())
    runs = [(name, args.robots, False) for name in names]
    if not args.no_robust:
        runs.append((args.robust_dataset, args.robots, True))
    if args.robust_all:
        runs += [(name, args.robots, "blind") for name in names]
    if not args.no_teams:
        runs += [(name, n, False) for name, n in TEAMS if args.only is None or name in args.only]
    rows = []
    for name, robots, robust in runs:
        res = run_pgo([args.data / f"{name}.g2o"], robots=robots, robust=bool(robust),
                      outliers=args.outliers if robust is True else 0.0, seed=0,
                      max_rounds=args.max_rounds, params=_params(args))
        fig = _figures(res)
        fig["method"] = args.method or CLI_METHOD
        rows.append(fig)
        if args.json:
            print(json.dumps(fig), flush=True)
    print(f"{'dataset':16s} {'method':9s} {'robots':>6s} {'robust':6s} {'central':>12s} {'distrib':>12s} "
          f"{'gap':>9s} {'tls_gap':>9s} {'jacc':>5s} {'rounds':>6s} {'r1e-2':>5s} {'r1e-3':>5s} "
          f"{'kB/rnd':>7s} {'MB':>7s} {'wall_s':>7s} {'cwall_s':>7s}", file=sys.stderr)
    for f in rows:
        robust = f.get("tls_gap") is not None
        central = f["centralized_tls_cost"] if robust else f["centralized_cost"]
        distrib = f["distributed_tls_cost"] if robust else f["distributed_cost"]
        print(f"{f['dataset']:16s} {f['method']:9s} {f['robots']:6d} {str(f['robust']):6s} "
              f"{_num(central, '12.6g')} {_num(distrib, '12.6g')} {_num(f['relative_gap'], '9.2e')} "
              f"{_num(f.get('tls_gap'), '9.2e')} {_num(f.get('inlier_jaccard'), '5.3f')} "
              f"{f['rounds']:6d} {str(f['rounds_to_1e-2']):>5s} {str(f['rounds_to_1e-3']):>5s} "
              f"{f['bytes_per_round'] / 1e3:7.2f} {f['bytes_sent'] / 1e6:7.2f} {f['wall_s']:7.1f} "
              f"{f['centralized_wall_s']:7.1f}", file=sys.stderr)
        if f.get("reference", "converged") != "converged":
            print(f"{'':16s} {f['reference']}", file=sys.stderr)


def _num(value: float | None, fmt: str) -> str:
    """``value`` formatted, or ``-`` right-aligned to the same width (a figure the run has not)."""
    width = int(fmt.split(".")[0])
    return format(value, fmt) if value is not None else "-".rjust(width)


if __name__ == "__main__":
    main()
