"""Fixed-neighbour priors equal their between factor, also for singular (R'R) information."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from kimera_multi_py.core.geometry import make_pose, so3_exp, to_gtsam
from kimera_multi_py.pgo.factors import between, fixed_neighbour


@pytest.mark.parametrize("kind", ["full", "diagonal", "singular"])
def test_fixed_neighbour_matches_between(kind: str) -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    info = {
        "full": A @ A.T + np.eye(6),
        "diagonal": np.diag(rng.uniform(1, 5, 6)),
        # cubicle-like: huge, anisotropic and only positive semi-definite
        "singular": (lambda R: R.T @ R)(np.triu(A * np.array([1, 1, 1e3, 1e3, 1e3, 1e6])) @
                                        np.diag([1, 1, 1, 1, 1, 1e-12])),
    }[kind]
    info = 0.5 * (info + info.T)
    Xi, Xj, Z = (make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3))
    values = gtsam.Values()
    values.insert(1, to_gtsam(Xi))
    values.insert(2, to_gtsam(Xj))
    ref = between(1, 2, Z, info).error(values)
    assert fixed_neighbour(1, True, Xj, Z, info).error(values) == pytest.approx(ref, rel=1e-6)
    assert fixed_neighbour(2, False, Xi, Z, info).error(values) == pytest.approx(ref, rel=1e-6)
