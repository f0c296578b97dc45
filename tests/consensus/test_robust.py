"""GNC-TLS weight formula and schedule."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.core.robust import (
    MU_STEP,
    GncSchedule,
    chi2_quantile,
    initial_mu,
    precision_recall,
    tls_threshold,
    tls_weights,
)


def test_weight_formula_values() -> None:
    barc2, mu = 4.0, 1.0
    # thresholds: mu/(mu+1) c2 = 2, (mu+1)/mu c2 = 8
    r2 = np.array([0.0, 2.0, 4.0, 8.0, 100.0])
    w = tls_weights(r2, mu, barc2)
    assert w[0] == 1.0 and w[1] == pytest.approx(1.0)
    assert w[2] == pytest.approx(np.sqrt(4.0 * 1.0 * 2.0 / 4.0) - 1.0)  # sqrt(2) - 1
    assert w[3] == pytest.approx(0.0) and w[4] == 0.0
    # continuity at both ends of the middle band
    eps = 1e-9
    assert tls_weights(np.array([2.0 + eps]), mu, barc2)[0] == pytest.approx(1.0, abs=1e-6)
    assert tls_weights(np.array([8.0 - eps]), mu, barc2)[0] == pytest.approx(0.0, abs=1e-6)


def test_weights_become_binary_as_mu_grows() -> None:
    r2 = np.array([1.0, 3.9, 4.1, 50.0])
    w = tls_weights(r2, 1e4, 4.0)
    assert w.tolist() == [1.0, 1.0, 0.0, 0.0]
    assert np.all(np.diff(tls_weights(np.linspace(0, 20, 50), 0.3, 4.0)) <= 1e-12)


def test_schedule_starts_convex_and_grows_mu() -> None:
    barc2 = tls_threshold(0.99, 6)
    assert barc2 == pytest.approx(16.8119, rel=1e-4)
    s = GncSchedule(barc2)
    r2 = np.array([1.0, 2.0, 1e4])
    w0 = s.update(r2)
    assert s.mu == pytest.approx(initial_mu(1e4, barc2) * MU_STEP)
    assert np.all(w0 > 0.0) and w0[0] > w0[1] > w0[2]  # convex surrogate: nothing cut yet
    for _ in range(60):
        w = s.update(r2)
    assert w.tolist() == [1.0, 1.0, 0.0] and GncSchedule.binary(w)


def test_precision_recall() -> None:
    p, r = precision_recall(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool))
    assert (p, r) == (0.5, 0.5)


def test_initial_mu_is_clamped_to_its_bounds():
    """Both distributed GNCs take ``μ₀`` through this one clamp (``gnc_mu0_min``, ``gnc_mu0_max``)."""
    s = GncSchedule(22.5)
    raw = s.initial_mu(np.array([1e8]))
    assert raw < 1e-6
    assert s.initial_mu(np.array([1e8]), lo=1e-4, hi=1e-3) == pytest.approx(1e-4)
    assert s.initial_mu(np.array([1.0]), lo=1e-4, hi=1e-3) == pytest.approx(1e-3)  # nothing exceeds c̄²: 1e6
    assert s.initial_mu(np.array([1e8]), hi=1e-3) == pytest.approx(raw)


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 12])
def test_chi2_quantile_is_scipy_stats_to_the_bit(dof: int) -> None:
    from scipy.stats import chi2

    for p in (0.5, 0.9, 0.95, 0.99, 0.997, 0.999, 0.9999):
        assert chi2_quantile(p, dof) == chi2.ppf(p, dof)
