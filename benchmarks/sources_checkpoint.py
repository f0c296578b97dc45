"""Keyframe sources and agent checkpoints, each against a reference measured in the same run.

- sources: seconds per keyframe of the simulator (``Simulation.keyframes``, the reference),
  of a recorded folder (``RecordedSource``), of a SimSource restart at keyframe ``k`` (replays
  0..k-1) and of a restart from a saved ``SimSource.state()`` (no replay);
- checkpoints: an agent after ``--keyframes`` keyframes; save and load seconds and file size
  (zlib level 1 and raw; best of ``--repeat``) and the in-memory snapshot copy, against
  ``pickle.dumps`` of the same agent in memory (the old format's write cost; nothing is ever
  unpickled).

    python benchmarks/sources_checkpoint.py --json [--scenario sims/office.toml] [--keyframes 120] [--repeat 3]
"""

from __future__ import annotations

import argparse
import itertools
import json
import pickle
import tempfile
import time
from pathlib import Path

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.checkpoint import load_checkpoint, save_checkpoint, snapshot
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.io.sources import RecordedSource
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import SimSource, keyframe_input, write_recording


def _timed(f, repeat: int = 1):  # type: ignore[no-untyped-def]
    """Best of ``repeat`` wall times (the machine is shared) and the last result."""
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = f()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenario", default="sims/office.toml")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keyframes", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    cfg = load_scenario(a.scenario)
    n = a.keyframes
    with tempfile.TemporaryDirectory() as tmp:
        out: dict[str, object] = {"scenario": a.scenario, "keyframes": n}
        sim = Simulation(cfg, a.seed)
        t_sim, kfs = _timed(lambda: [keyframe_input(kf) for kf in itertools.islice(sim.keyframes(0), n)])
        t_rec_write, _ = _timed(lambda: write_recording(Path(tmp) / "rec", cfg, len(cfg.robots), a.seed))
        t_rec, _ = _timed(lambda: list(itertools.islice(RecordedSource(Path(tmp) / "rec", 0), n)))
        src = SimSource(cfg, a.seed, 0, simulation=sim)
        for _ in itertools.islice(src, n):
            pass
        state = src.state()
        t_restart, _ = _timed(lambda: next(SimSource(cfg, a.seed, 0, start=n, simulation=sim)))
        t_resume, _ = _timed(lambda: next(SimSource(cfg, a.seed, 0, start=n, resume=state, simulation=sim)))
        out["sources"] = {
            "simulator_s_per_kf (reference)": t_sim / n,
            "recorded_s_per_kf": t_rec / n,
            "record_team_s": t_rec_write,
            "recording_bytes": sum(p.stat().st_size for p in (Path(tmp) / "rec").rglob("*") if p.is_file()),
            f"restart_at_{n}_replay_s": t_restart,
            f"restart_at_{n}_resume_s": t_resume,
        }
        agent = Agent(0, tuple(range(len(cfg.robots))), AgentParams())
        for kf in kfs:
            agent.process_keyframe(kf)
        r = a.repeat
        ck: dict[str, object] = {"snapshot_copy_s (on the agent's thread)": _timed(lambda: snapshot(agent), r)[0]}
        for compress in (True, False):
            path = Path(tmp) / f"a{int(compress)}.ckpt"
            t_save, _ = _timed(lambda p=path, c=compress: save_checkpoint(p, agent, {"next": n}, compress=c), r)
            t_load, _ = _timed(lambda p=path: load_checkpoint(p), r)
            ck["zlib" if compress else "raw"] = {"save_s": t_save, "load_s": t_load, "bytes": path.stat().st_size}
        t_pickle, blob = _timed(lambda: pickle.dumps(agent, protocol=pickle.HIGHEST_PROTOCOL), r)
        ck["pickle_dumps (reference)"] = {"save_s": t_pickle, "bytes": len(blob)}
        out["checkpoint"] = ck
    print(json.dumps(out, indent=None if a.json else 1))


if __name__ == "__main__":
    main()
