"""The centralised GNC's safety check: TLS decisions re-made at the converged solution."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from kimera_multi_py.core.geometry import to_gtsam
from kimera_multi_py.core.robust import tls_threshold
from kimera_multi_py.pgo.centralised import components, recheck, solve_centralized
from kimera_multi_py.pgo.factors import to_values
from tests.consensus.test_pgo_aliased import aliased_ring


def test_recheck_rejects_aliases_accepted_by_least_squares() -> None:
    # the failure seen in centralised mode: every closure accepted (weights all 1), aliases
    # included; the converged (least-squares) solution re-decided with the plain TLS threshold
    g = aliased_ring()
    ls = solve_centralized(g, robust=False)
    priors = [gtsam.PriorFactorPose3(int(g.keys[int(c[0])]), to_gtsam(ls.poses[int(c[0])]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)) for c in components(g)]
    _, w = recheck(g, priors, to_values(g.keys, ls.poses), gtsam.LevenbergMarquardtParams(), tls_threshold(0.999))
    assert g.outlier.sum() >= 8 and not np.any(w[g.outlier] > 0.5)


@pytest.mark.slow
def test_robust_solve_keeps_every_true_closure() -> None:
    g = aliased_ring()
    res = solve_centralized(g, robust=True)
    assert res.weights is not None
    assert not np.any(res.weights[g.outlier] > 0.5) and np.all(res.weights[~g.outlier] > 0.5)
