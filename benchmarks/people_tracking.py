"""People tracking alone, at the robots' TRUE poses: detection, each robot's tracker and CLEAR MOT
against the simulator's people, seed by seed (docs/algorithms/people.md).

No SLAM runs: every robot's keyframes are simulated as in a run (same plans, same sensor noise for
a seed) and placed at their true poses, so what is measured is the people pipeline by itself, in
a minute per seed instead of a whole team run. The figures are those of ``results.json["people"]``
(``eval/people.py``): per robot, frames are its keyframes, objects the people in view of it and
hypotheses its confirmed tracks' samples; ``id_switches_per_person`` divides the switches by the
people each robot saw, summed over the robots. ``switches`` lists each switch with the time the
person had been out of the robot's sight (``gap_s``) and whether the new track had followed
someone else before (``swap``) or was new (a person met again after a long gap, or seen again
after their track died: nothing in the simulator tells look-alike people apart).
``id_switches_team_ids`` counts them again with each track named by the team person it was fused
into (every robot's tracks fused as ``people/fusion.py`` does once all the tables arrived: the ids
the scene graph gives, where another robot's track may bridge a gap). Detection precision and
recall and the worst person's trajectory RMSE (the team's fused people) are those of
``results.json["people"]`` too, but at the true poses: with SLAM, a person is also off by the
error of the pose of the robot that saw them.
Targets (per seed): detection precision and recall >= 0.9, worst trajectory RMSE <= 0.15 m,
MOTA >= 0.8 and at most one ID switch per person.

    python benchmarks/people_tracking.py --json
    python benchmarks/people_tracking.py --scenario sims/office.toml --seeds 0 1 --json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.outputs import RobotOutcome
from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.eval.people import people_in_view, people_results
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.people import PeopleParams, PeopleTracker
from kimera_multi_py.people.fusion import TeamTrack, fuse_people
from kimera_multi_py.sim import Simulation, load_scenario

REPO = Path(__file__).resolve().parents[1]
TARGETS = {"precision": 0.9, "recall": 0.9, "trajectory_rmse_max": 0.15, "mota": 0.8, "id_switches_per_person": 1.0}
_HUMAN = CLASS_IDS["human"]


def track_robot(sim: Simulation, robot: int, params: PeopleParams, keyframes_per_submap: int = 10
                ) -> tuple[PeopleTracker, list[np.ndarray]]:
    """One robot's tracker fed every keyframe at its true pose; the people in view of each keyframe."""
    tr = PeopleTracker((_HUMAN,), params)
    views = []
    rng = sim.rng(robot)
    for k in range(len(sim.plans[robot].stamps)):
        kf = sim.keyframe(robot, k, rng)
        pose, hit = kf.true_pose, kf.scan.hit
        sid = k // keyframes_per_submap
        if k % keyframes_per_submap == 0:
            tr.set_submap_pose(sid, pose)
        tr.update(k, kf.stamp, sid, transform_points(pose, kf.scan.points()[hit]), kf.scan.labels[hit], pose[:3, 3])
        views.append(people_in_view(sim, pose, kf.stamp))
    return tr, views


def mot(sim: Simulation, tr: PeopleTracker, views: list[np.ndarray], gate: float = 0.5) -> Any:
    """A motmetrics accumulator for one robot, as ``eval/people.py`` fills it."""
    import motmetrics as mm

    samples = {(t.id, float(s)): p for t in tr.confirmed() for s, p in zip(t.stamps, tr.positions(t), strict=True)}
    acc = mm.MOTAccumulator(auto_id=True)
    for rec, view in zip(tr.log, views, strict=True):
        true = np.array([h.position(rec.stamp) for h in sim.humans]).reshape(-1, 3)
        hyp = [(int(t), samples[(int(t), rec.stamp)]) for t in rec.tracks if (int(t), rec.stamp) in samples]
        xyz = np.array([p for _, p in hyp], dtype=np.float64).reshape(-1, 3)
        d = np.asarray(mm.distances.norm2squared_matrix(true[view][:, :2], xyz[:, :2], max_d2=gate ** 2))
        acc.update(view.tolist(), [h for h, _ in hyp], d.reshape(len(view), len(hyp)))
    return acc


def switches(acc: Any, stamps: list[float]) -> list[dict[str, Any]]:
    """Each ID switch: when, who, the time since the person's previous match, and whether the new
    hypothesis had followed another person before."""
    ev = acc.mot_events.reset_index()
    m = ev[ev.Type.isin(["MATCH", "SWITCH"])]
    out = []
    for _, row in m[m.Type == "SWITCH"].iterrows():
        prev = m[(m.OId == row.OId) & (m.FrameId < row.FrameId)].iloc[-1]
        before = m[(m.HId == row.HId) & (m.FrameId < row.FrameId)]
        out.append({"t": round(stamps[int(row.FrameId)], 1), "person": int(row.OId),
                    "gap_s": round(stamps[int(row.FrameId)] - stamps[int(prev.FrameId)], 1),
                    "swap": bool(len(before) and (before.OId != row.OId).any())})
    return out


def outcome(robot: int, tr: PeopleTracker) -> RobotOutcome:
    """The people part of a robot's outcome, as ``agent/outputs.py`` fills it (no sharing)."""
    people = {"tracks": tr.people(), "dropped": dict(tr.dropped),
              "keyframes": [{"index": r.index, "stamp": r.stamp, "tracks": r.tracks.tolist(),
                             "detections": transform_points(tr.correction(r.submap), r.refs).tolist()}
                            for r in tr.log]}
    return RobotOutcome(robot, np.zeros(0), np.zeros((0, 4, 4)), None, [], [], {},  # type: ignore[arg-type]
                        people=people)


def run_seed(scenario: Path, seed: int, robots: int, params: PeopleParams) -> dict[str, Any]:
    sim = Simulation(load_scenario(scenario, robots=robots), seed=seed)
    per_robot: dict[str, dict[str, Any]] = {}
    outcomes = []
    for r in range(sim.num_robots):
        tr, views = track_robot(sim, r, params)
        acc = mot(sim, tr, views)
        outcomes.append(outcome(r, tr))
        per_robot[str(r)] = {"switches": switches(acc, [rec.stamp for rec in tr.log]), "reacquired": tr.reacquired}
    # the team's people, as every robot holds them once all the tables arrived (one frame: the truth)
    team = fuse_people({team_id(o.robot, int(t["id"])): TeamTrack(o.robot, np.asarray(t["stamps"], np.float64),
                                                                  np.asarray(t["positions"], np.float64).reshape(-1, 3))
                        for o in outcomes for t in o.people["tracks"]})
    for o in outcomes:
        o.people["team"] = team
    truth = [np.asarray(p.poses) for p in sim.plans]
    res = people_results(sim, truth, outcomes, np.eye(4), list(range(sim.num_robots)))
    people = res["mot"]["overall"]["num_unique_objects"]
    team_mot = res["mot_team_ids"].get("overall", {})
    return {"seed": seed, "precision": res["detection"]["precision"], "recall": res["detection"]["recall"],
            "people_in_view": res["detection"]["people_in_view"], "dropped": res["detection"]["dropped"],
            "mota": res["mota"], "id_switches": res["id_switches"], "people_seen": people,
            "id_switches_per_person": res["id_switches_per_person"],
            "id_switches_team_ids": team_mot.get("num_switches"),
            "id_switches_per_person_team_ids": (team_mot["num_switches"] / people) if people else None,
            "trajectory_rmse": res["trajectory_rmse"], "trajectory_rmse_max": res["trajectory_rmse_max"],
            "trajectory_rmse_whole_tracks_max": res["trajectory_rmse_whole_tracks_max"],
            "people_tracked": res["people_tracked"],
            "swaps": sum(s["swap"] for v in per_robot.values() for s in v["switches"]),
            "per_robot": per_robot}


def meets(r: dict[str, Any]) -> bool:
    """Whether one seed's run meets every target."""
    return (r["precision"] >= TARGETS["precision"] and r["recall"] >= TARGETS["recall"]
            and r["trajectory_rmse_max"] <= TARGETS["trajectory_rmse_max"] and r["mota"] >= TARGETS["mota"]
            and (r["id_switches_per_person"] or 0) <= TARGETS["id_switches_per_person"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", type=Path, default=REPO / "sims" / "people.toml")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    runs = [run_seed(args.scenario, s, args.robots, PeopleParams()) for s in args.seeds]
    met = all(meets(r) for r in runs)
    out = {"scenario": str(args.scenario), "robots": args.robots, "targets": TARGETS, "runs": runs, "met": met}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for r in runs:
            print(f"seed {r['seed']}: precision {r['precision']:.3f}, recall {r['recall']:.3f}, "
                  f"worst RMSE {r['trajectory_rmse_max']:.3f} m, MOTA {r['mota']:.3f}, ID switches {r['id_switches']} "
                  f"({r['id_switches_per_person']:.2f} per person; team ids {r['id_switches_team_ids']}), "
                  f"swaps {r['swaps']}")


if __name__ == "__main__":
    main()
