"""The evidence behind a frame decision, hypothesis by hypothesis (docs/algorithms/pgo.md).

A robot's report (``results.json["alignment"][robot]["evidence"]``) lists every frame hypothesis
it weighed, the map-refuted ones included, each with:

* ``places``, ``edges``, ``peers``: the closures behind it; ``triples``: the robot triples it
  closes (two peers whose closures agree on it: A–B ∘ B–C ≈ A–C, since both peers sit in one team
  frame);
* ``map``: the occupancy agreement of the robot's map with the team's under it (overlap and
  conflicts in coarse cells, :mod:`.map_check`), or None where the maps do not overlap;
* ``landmarks``: [places, matched, conflicting] object landmarks (:mod:`.landmark_check`), when
  landmarks were consulted;
* ``verdict``: ``adopted``, ``refuted by the maps``, ``refuted by landmarks``, ``outvoted``
  (another hypothesis adopted on more evidence) or ``undecided`` (nothing tells it from a rival:
  the robot stays out).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from kimera_multi_py.alignment.frames import FrameHypothesis
from kimera_multi_py.alignment.landmark_check import LandmarkScore
from kimera_multi_py.alignment.map_check import MapAgreement


def hypothesis_evidence(hyps: Sequence[FrameHypothesis], chosen: FrameHypothesis | None,
                        map_score: Callable[[np.ndarray], MapAgreement | None],
                        landmarks: Sequence[LandmarkScore] = (),
                        refuted: Sequence[dict[str, object]] = ()) -> list[dict[str, object]]:
    """One JSON-ready entry per hypothesis in ``hyps`` (in order; ``landmarks`` aligned with them
    when given), then one per map-refuted hypothesis (``refuted``: their report entries)."""
    out: list[dict[str, object]] = []
    for i, h in enumerate(hyps):
        ag = map_score(h.T)
        lm = landmarks[i] if i < len(landmarks) else None
        if chosen is not None and h is chosen:
            verdict = "adopted"
        elif lm is not None and lm.refuted():
            verdict = "refuted by landmarks"
        elif chosen is not None:
            verdict = "outvoted"
        else:
            verdict = "undecided"
        k = len(h.peers)
        out.append({"places": int(h.places), "edges": int(h.size), "peers": list(h.peers),
                    "triples": k * (k - 1) // 2, "translation": np.round(h.T[:3, 3], 2).tolist(),
                    "map": None if ag is None else ag.as_dict(),
                    "landmarks": None if lm is None else lm.as_list(), "verdict": verdict})
    for r in refuted:
        peers = r.get("peers", [])
        k = len(peers) if isinstance(peers, list) else 0
        out.append({"places": r.get("places"), "edges": r.get("edges"), "peers": peers, "triples": k * (k - 1) // 2,
                    "translation": r.get("hypothesis"),
                    "map": {key: r[key] for key in ("overlap", "conflicts", "ratio") if key in r},
                    "landmarks": None, "verdict": "refuted by the maps"})
    return out
