"""The distributed solver's knobs (:class:`PgoParams`), shared by both methods (:mod:`.agent`, :mod:`.gn`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any


@dataclass
class PgoParams:
    """Knobs of the distributed solver (defaults tuned on the DPGO benchmark graphs)."""

    max_rounds: int = 500
    # "block_sor": block Gauss–Seidel with adaptive over-relaxation (this module);
    # "gn_pcg": Levenberg–Marquardt with pipelined block-Jacobi CG across the robots (.gn)
    method: str = "block_sor"
    gn_forcing: float = 0.25  # CG stops when the preconditioned residual fell by this factor
    # (measured on cubicle, 5 robots, with recycling: 0.25 reaches 1e-3 in 191 rounds, 0.1 in
    # 217, 0.05 not in 230; Eisenstat–Walker's schedule capped at 0.1: 231)
    gn_max_cg: int = 60  # CG iterations per outer step at most
    gn_damping: float = 1e-4  # initial λ of λ·diag(H)
    gn_damping_factor: float = 3.0  # λ /= this on an accepted step, *= its square on a rejected one
    gn_damping_min: float = 1e-8
    gn_damping_max: float = 1e6  # a rejected step beyond this λ: converged
    gn_rel_tol: float = 1e-6  # done after two accepted steps in a row lower the cost by less (relative)
    gn_max_outer: int = 100
    # line search: the team cost at every one of these multiples of the step, in one round
    gn_step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 1.5, 2.0, 3.0)
    gn_coarse_size: int = 20  # poses per rigid chunk of the coarse space (0: block Jacobi only)
    gn_coarse_refresh: int = 3  # outer steps between rebuilds of the coarse space
    gn_recycle: int = 2  # the team's last steps added to the coarse space (Krylov recycling)
    # robust: GNC weights are updated after this many accepted outer steps, or sooner after one
    # that lowered the team cost by less than gn_weight_tol (relative). Measured on cubicle, 5
    # robots (with gnc_mu0_min=1e-4): one step per update ends 3.7e-2 above gtsam's TLS cost,
    # two end 9.4e-3 below it in 488 rounds; bigger μ steps instead (gnc_mu_step 1.7, 2.0) are
    # worse (4.6e-2, 1.1e-1): the solve must follow the weights
    gn_weight_every: int = 2
    gn_weight_tol: float = 1e-3
    # robust: a re-check fires once a step lowers the team cost by less than this (relative), not
    # only at full convergence (cubicle, 5 robots: the same inliers and cost, 550 → 488 rounds)
    gn_recheck_tol: float = 1e-4
    rel_tol: float = 1e-8  # ready when the relative pose change of an update is below this
    lm_iterations: int = 20  # per local solve (warm-started; usually 1-3 are used)
    lm_rel_tol: float = 1e-10
    chordal_init: bool = True  # local chordal initialisation (else the robot's odometry)
    acceleration: bool = False  # Nesterov momentum on published poses (measured: SOR is better)
    # block SOR: publish X ⊕ ω(X* ⊖ X). None adapts ω per robot (Young's estimate from the
    # ratio of successive block steps); a number fixes it (1.0: plain Gauss–Seidel)
    over_relaxation: float | None = None
    max_over_relaxation: float = 1.98
    restart_interval: int = 50  # momentum restart every this many updates (besides on cost rise)
    resend_interval: int = 5  # re-publish unchanged public poses this often (message loss)
    robust: bool = False
    inlier_probability: float = 0.999  # χ²₆ quantile of the TLS threshold c̄² (22.5)
    tls_dof: int = 6  # degrees of freedom of that χ² (3 for a planar, 2-D graph)
    gnc_round_cap: int = 10  # rounds between weight updates at most
    # robust: which inter-robot edges start at weight 0 (GNC revisits them): "support" those no
    # other edge agrees with (random outliers; every consistent group stays for the joint GNC),
    # "alignment" those outside the alignment's majority hypothesis, "none"
    screen: str = "support"
    gnc_mu0_trusted: bool = True  # μ₀ from the largest residual of the current inliers only
    # one μ for the team: robots propose their μ₀ and apply the smallest this many rounds later
    gnc_team_mu: bool = True
    gnc_mu_delay: int = 3
    # ceiling of μ₀: start at least this convex. μ₀ from the current residuals is too large when
    # the start already sits in an aliased hypothesis (a warm restart after a wrong solve: the
    # aliased closures fit, so GNC starts near-binary and keeps them; gtsam's GNC takes μ₀ from
    # the initial values' residuals, usually far larger). Measured on the office graphs.
    gnc_mu0_max: float = 1e-3
    # floor of μ₀ (0: none). One gross outlier among the trusted edges makes μ₀ = c̄²/(2r²max − c̄²)
    # tiny (cubicle, 5 robots: 7.5e-7, from r² = 6.6e5 c̄²; the 99.9th percentile is 6e2–1e3 c̄²
    # on four robots, 2e5 on one), and at μ ×1.4 per update GNC then spends its 40 updates below
    # μ = 0.53, where a closure above the threshold weighs about c̄√μ/r against the odometry.
    # With the floor, an edge whose start residual exceeds c̄²(1 + 1/μ₀) ≈ 1e4 c̄² (Mahalanobis
    # ≈ 470) starts rejected and the schedule spans the decades where decisions are made.
    # Measured with gn_pcg (5 robots, cap 500): cubicle 1.31e-2 above gtsam's TLS cost → 9.4e-3
    # below it; the other five graphs within 1.4e-5, all Jaccard ≥ 0.9996. The agents' team PGO
    # (team_params) keeps no floor: not measured there
    gnc_mu0_min: float = 1e-4
    gnc_max_steps: int = 40
    gnc_mu_step: float = 1.4  # μ ← this·μ per weight update (gtsam's GNC: 1.4)
    gnc_rechecks: int = 2  # after GNC: re-decide every edge at the converged solution (χ² test)
    gnc_max_rechecks: int = 4  # gn_pcg: more plain re-checks while the last one flipped a decision
    recheck_factor: float = 3.0  # first re-check admits r² ≤ factor·c̄², the last one r² ≤ c̄²
    align_patience: int = 20  # rounds with < 3 alignment inliers before a plain alignment
    # robust mode: frame alignment by hypotheses (alignment.frame_hypotheses). A robot aligns to
    # the hypothesis supported by the most distinct places, when it leads the runner-up by
    # ``align_min_margin`` places and rests on ``align_min_places`` or more; it decides before
    # every neighbour pose is known only with a lead of ``align_early_margin``. A robot with no
    # such hypothesis stays out of the team frame for the epoch (its own frame, edges off).
    align_hypotheses: bool = True
    align_min_places: int = 2
    align_min_margin: int = 1
    align_early_margin: int = 1
    # no hypothesis clearly leads when the epoch's evidence is in: "consensus" aligns by the robust
    # consensus of every edge and leaves the choice to GNC, but only while the leader rests on
    # more places than any other hypothesis; an exact tie in places is no evidence for either,
    # and the robot stays out of the team frame for the epoch, as the centralised server's frame
    # screen does. After exact ties GNC has picked the alias and carried the whole team into it
    # (aliased_wing, 3 robots, seed 9: 3 places each, 24 true edges against 17; team ATE 2.82 m,
    # 7.3x dead reckoning; seed 5 on an earlier front end: 3 against 3, 2.81 m). "exclude" keeps
    # the robot out on any tie without a clear lead
    align_tie: str = "consensus"
    # ... but only between hypotheses that each rest on this many places or more: a tie between
    # single-place groups is the aliasing case itself (twin rooms: each group is one room), where
    # more edges are no evidence at all; the robot stays out of the team frame (safety
    # property: a frame resting on a single aliased group is not merged)
    align_tie_min_places: int = 2
    # one group from a single place and no competitor: True adopts it once no more edges can
    # arrive; False keeps the robot out of the team frame until a second place agrees. False
    # fixed office, 5 robots, seed 5 (a robot aligned on one room sat in the twin office 6 m
    # off, and a second robot joined it there), but it keeps out every robot whose overlap with
    # the team is one room: the small scenario's team lost all its closures (tests/sim), so the
    # default adopts
    align_lone_place: bool = True
    place_radius: float = 2.0  # m: own closure poses closer than this are one place
    # safety: an estimate that bends away from the robot's own odometry beyond its drift model
    # (odometry_disagreement > 1) is not adopted; the robot falls back to its own frame
    drift_check: bool = True
    drift_z: float = 4.0
    drift_floor: float = 0.5  # m
    # chordal block Gauss–Seidel over the team before the BCD (measured: no faster on the
    # benchmark graphs, worse on cubicle whose chordal relaxation is poor; off by default)
    distributed_init: bool = False
    init_rel_tol: float = 1e-3  # an initialising robot is ready below this relative change
    init_max_rounds: int = 40  # the leader starts the BCD after this many rounds at most
    start_resend: int = 5  # the leader repeats ``start`` this many rounds (message loss)


def team_params(**overrides: Any) -> PgoParams:
    """The PGO of a SLAM team's agents: robust, with 600 rounds per epoch, no μ₀ floor."""
    return dataclasses.replace(PgoParams(robust=True, max_rounds=600, gnc_mu0_min=0.0), **overrides)
