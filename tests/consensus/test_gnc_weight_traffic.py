"""GNC weights on the wire (kimera_multi_py.pgo.weights): an edge's owner sends the weights that
changed since it last sent them (all of them every ``weights_full_every``-th update); without
loss the team's solution is the one it reaches with every weight sent at every update."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.workflow.pgo_benchmark import run_pgo


def test_changed_weights_only_give_the_same_solution_for_fewer_bytes(pgo_data: Path) -> None:
    g2o = pgo_data / "smallGrid3D.g2o"
    runs = {every: run_pgo([g2o], robots=3, robust=True, outliers=0.5, seed=2, max_rounds=600,
                           params=PgoParams(weights_full_every=every))
            for every in (1, 4)}
    full, changed = runs[1], runs[4]
    assert full.rounds == changed.rounds
    assert np.array_equal(full.distributed_weights, changed.distributed_weights)
    assert np.array_equal(full.poses, changed.poses)
    assert full.relative_gap == changed.relative_gap
    sent = {k: r.bytes_by_topic["pgo/gnc_weights"] for k, r in runs.items()}
    assert sent[4] < 0.7 * sent[1]
