"""Map cells on the wire: zstd (what ``mapshare.wire.pack_cells`` uses) against zlib level 6
(what it used before), on a robot's real map evidence, in the same run.

One robot of the default office scenario maps ``--keyframes`` keyframes; its submaps' cells
(the payloads of ``SubmapEvidence``) and its whole fused map are packed as ``pack_cells`` packs
them, once with each compressor. Reported per payload size: bytes and the fastest of
``--repeats`` compressions.

    python benchmarks/wire_cells.py --json
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
import zlib
from pathlib import Path

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.comms.compression import ZSTD, compress
from kimera_multi_py.mapshare.wire import _shuffle
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.source import SimSource
from kimera_multi_py.team.build import agent_params

REPO = Path(__file__).resolve().parents[1]


def raw_cells(codes: np.ndarray, rows: np.ndarray) -> bytes:
    """The bytes ``pack_cells`` compresses: shuffled code steps and shuffled rows, column by column."""
    steps = np.diff(np.asarray(codes, dtype="<i8"), prepend=np.int64(0))
    return _shuffle(steps) + _shuffle(np.ascontiguousarray(np.asarray(rows, dtype="<i2").T).reshape(-1))


def fastest(f, data: bytes, repeats: int) -> tuple[float, int]:
    best, size = float("inf"), 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        size = len(f(data))
        best = min(best, time.perf_counter() - t0)
    return best, size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--keyframes", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cfg = load_scenario(args.scenario)
    agent = Agent(0, None, agent_params(cfg))
    for kf in itertools.islice(SimSource(cfg, 0, 0), args.keyframes):
        agent.process_keyframe(kf)
    payloads = {f"submap {sid}": raw_cells(s.codes, s.rows[:, 1:]) for sid, s in sorted(agent.map.submaps.items())}
    codes, rows, _ = agent.map.evidence()
    payloads["whole map"] = raw_cells(codes, rows[:, 1:].clip(-32768, 32767))
    out = []
    for name, raw in payloads.items():
        tz, sz = fastest(lambda b: zlib.compress(b, 6), raw, args.repeats)
        ts, ss = fastest(lambda b: compress(b, ZSTD, 3), raw, args.repeats)
        out.append({"payload": name, "cells": len(raw) // (8 + 2 * (rows.shape[1] - 1)), "raw_bytes": len(raw),
                    "zlib6_bytes": sz, "zstd3_bytes": ss, "zlib6_ms": round(tz * 1e3, 2),
                    "zstd3_ms": round(ts * 1e3, 2), "size_ratio": round(sz / ss, 2), "speed_ratio": round(tz / ts, 1)})
    total = {k: sum(r[k] for r in out if r["payload"] != "whole map") for k in ("zlib6_bytes", "zstd3_bytes")}
    tms = {k: sum(r[k] for r in out if r["payload"] != "whole map") for k in ("zlib6_ms", "zstd3_ms")}
    summary = {"keyframes": args.keyframes, "submaps": len(agent.map.submaps), "payloads": out,
               "submaps_total": {**total, **{k: round(v, 1) for k, v in tms.items()},
                                 "size_ratio": round(total["zlib6_bytes"] / total["zstd3_bytes"], 2),
                                 "speed_ratio": round(tms["zlib6_ms"] / tms["zstd3_ms"], 1)}}
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        for r in out:
            print(r)
        print(summary["submaps_total"])


if __name__ == "__main__":
    main()
