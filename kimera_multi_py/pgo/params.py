"""The distributed solver's knobs (:class:`PgoAgent`'s and the gn_pcg agent's: :mod:`.agent`, :mod:`.gn`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal


@dataclass
class PgoParams:
    """Knobs of the distributed solver (defaults tuned on the DPGO benchmark graphs)."""

    max_rounds: int = 500
    """Rounds per solve (per epoch in the team PGO) at most."""
    method: Literal["block_sor", "gn_pcg"] = "block_sor"
    """``block_sor``: block Gauss–Seidel with adaptive over-relaxation; ``gn_pcg``:
    Levenberg–Marquardt with pipelined block-Jacobi CG across the robots."""
    # (measured on cubicle, 5 robots, with recycling: 0.25 reaches 1e-3 in 191 rounds, 0.1 in
    # 217, 0.05 not in 230; Eisenstat–Walker's schedule capped at 0.1: 231)
    gn_forcing: float = 0.25
    """gn_pcg: CG stops when the preconditioned residual fell by this factor."""
    gn_max_cg: int = 60
    """gn_pcg: CG iterations per outer step at most."""
    gn_damping: float = 1e-4
    """gn_pcg: initial λ of the damping λ·diag(H)."""
    gn_damping_factor: float = 3.0
    """gn_pcg: λ is divided by this on an accepted step, multiplied by its square on a rejected one."""
    gn_damping_min: float = 1e-8
    """gn_pcg: smallest λ."""
    gn_damping_max: float = 1e6
    """gn_pcg: a step rejected beyond this λ means converged."""
    gn_rel_tol: float = 1e-6
    """gn_pcg: done after two accepted steps in a row lower the cost by less than this (relative)."""
    gn_max_outer: int = 100
    """gn_pcg: outer (Levenberg–Marquardt) steps at most."""
    gn_step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 1.5, 2.0, 3.0)
    """gn_pcg line search: the team cost at every one of these multiples of the step, in one round."""
    gn_coarse_size: int = 20
    """gn_pcg: poses per rigid chunk of the coarse space (0: block Jacobi only)."""
    gn_coarse_refresh: int = 3
    """gn_pcg: outer steps between rebuilds of the coarse space."""
    gn_recycle: int = 2
    """gn_pcg: the team's last steps added to the coarse space (Krylov recycling)."""
    # Measured on cubicle, 5 robots (with gnc_mu0_min=1e-4): one step per update ends 3.7e-2
    # above gtsam's TLS cost, two end 9.4e-3 below it in 488 rounds; bigger μ steps instead
    # (gnc_mu_step 1.7, 2.0) are worse (4.6e-2, 1.1e-1): the solve must follow the weights
    gn_weight_every: int = 2
    """gn_pcg, robust: GNC weights are updated after this many accepted outer steps ..."""
    gn_weight_tol: float = 1e-3
    """... or sooner after one that lowered the team cost by less than this (relative)."""
    # (cubicle, 5 robots: the same inliers and cost, 550 → 488 rounds)
    gn_recheck_tol: float = 1e-4
    """gn_pcg, robust: a re-check fires once a step lowers the team cost by less than this
    (relative), not only at full convergence."""
    rel_tol: float = 1e-8
    """A robot is ready when the relative pose change of an update is below this."""
    lm_iterations: int = 20
    """Levenberg–Marquardt iterations per local solve (warm-started; usually 1-3 are used)."""
    lm_rel_tol: float = 1e-10
    """Relative error tolerance of the local Levenberg–Marquardt solve."""
    chordal_init: bool = True
    """Local chordal initialisation (else the robot's odometry)."""
    acceleration: bool = False
    """Nesterov momentum on published poses (measured: SOR is better)."""
    over_relaxation: float | None = None
    """block_sor publishes X ⊕ ω(X* ⊖ X): null adapts ω per robot (Young's estimate from the ratio
    of successive block steps); a number fixes it (1.0: plain Gauss–Seidel)."""
    max_over_relaxation: float = 1.98
    """Largest adaptive ω."""
    restart_interval: int = 50
    """Momentum restart every this many updates (besides on a cost rise)."""
    resend_interval: int = 5
    """Rounds between re-publications of unchanged public poses (message loss)."""
    weights_full_every: int = 4
    """An inter-robot edge's owner sends the GNC weights that changed since it last sent them to
    the peer, and every one of them at each this many-th weight update (message loss); 1: every
    weight at every update."""
    robust: bool = False
    """GNC with a truncated least-squares cost on the loop closures."""
    inlier_probability: float = 0.999
    """χ² quantile of the TLS threshold c̄² (22.5 for six degrees of freedom)."""
    tls_dof: int = 6
    """Degrees of freedom of that χ² (3 for a planar, 2-D graph)."""
    gnc_round_cap: int = 10
    """Rounds between GNC weight updates at most."""
    screen: Literal["support", "alignment", "none"] = "support"
    """Robust: which inter-robot edges start at weight 0 (GNC revisits them): ``support``, those no
    other edge agrees with (random outliers; every consistent group stays for the joint GNC);
    ``alignment``, those outside the alignment's majority hypothesis; ``none``."""
    gnc_mu0_trusted: bool = True
    """μ₀ from the largest residual of the current inliers only."""
    gnc_team_mu: bool = True
    """One μ for the team: robots propose their μ₀ and apply the smallest ``gnc_mu_delay`` rounds later."""
    gnc_mu_delay: int = 3
    """Rounds between proposing μ₀ and applying the team's."""
    # μ₀ from the current residuals is too large when the start already sits in an aliased
    # hypothesis (a warm restart after a wrong solve: the aliased closures fit, so GNC starts
    # near-binary and keeps them; gtsam's GNC takes μ₀ from the initial values' residuals, usually
    # far larger). Measured on the office graphs.
    gnc_mu0_max: float = 1e-3
    """Ceiling of μ₀: GNC starts at least this convex."""
    # One gross outlier among the trusted edges makes μ₀ = c̄²/(2r²max − c̄²)
    # tiny (cubicle, 5 robots: 7.5e-7, from r² = 6.6e5 c̄²; the 99.9th percentile is 6e2–1e3 c̄²
    # on four robots, 2e5 on one), and at μ ×1.4 per update GNC then spends its 40 updates below
    # μ = 0.53, where a closure above the threshold weighs about c̄√μ/r against the odometry.
    # With the floor, an edge whose start residual exceeds c̄²(1 + 1/μ₀) ≈ 1e4 c̄² (Mahalanobis
    # ≈ 470) starts rejected and the schedule spans the decades where decisions are made.
    # Measured with gn_pcg (5 robots, cap 500): cubicle 1.31e-2 above gtsam's TLS cost → 9.4e-3
    # below it; the other five graphs within 1.4e-5, all Jaccard ≥ 0.9996. The agents' team PGO
    # (team_params) keeps no floor: not measured there
    gnc_mu0_min: float = 1e-4
    """Floor of μ₀ (0: none)."""
    gnc_max_steps: int = 40
    """GNC weight updates at most."""
    gnc_mu_step: float = 1.4
    """μ is multiplied by this per weight update (gtsam's GNC: 1.4)."""
    gnc_rechecks: int = 2
    """After GNC: re-decide every edge at the converged solution this often (χ² test)."""
    gnc_max_rechecks: int = 4
    """gn_pcg: more plain re-checks while the last one flipped a decision, up to this many."""
    recheck_factor: float = 3.0
    """The first re-check admits r² ≤ factor·c̄², the last one r² ≤ c̄²."""
    align_patience: int = 20
    """Rounds with fewer than 3 alignment inliers before a plain alignment."""
    # A robot aligns to the hypothesis supported by the most distinct places, when it leads the
    # runner-up by ``align_min_margin`` places and rests on ``align_min_places`` or more; it decides
    # before every neighbour pose is known only with a lead of ``align_early_margin``. A robot with
    # no such hypothesis stays out of the team frame for the epoch (its own frame, edges off).
    align_hypotheses: bool = True
    """Robust mode: frame alignment by hypotheses (alignment.frames)."""
    align_min_places: int = 2
    """Distinct places the chosen hypothesis rests on at least."""
    align_min_margin: int = 1
    """Places by which the chosen hypothesis leads the runner-up at least."""
    align_early_margin: int = 1
    """Lead needed to decide before every neighbour pose is known."""
    # A tie is no evidence: "consensus" aligned by the robust consensus of every edge and left
    # the choice between groups of several places to GNC, which carried whole teams into an alias
    # on floors with rows of identical rooms; the robot now stays out of the team frame and a
    # later epoch, with more closures, landmarks or map, decides again
    align_tie: Literal["consensus", "exclude"] = "exclude"
    """No hypothesis clearly leads when the epoch's evidence is in: ``exclude`` (default) keeps the
    robot out of the team frame; ``consensus`` (for studies of the back end alone, not safe) aligns
    by the robust consensus of every edge and leaves the choice to GNC."""
    # a tie between single-place groups is the aliasing case itself (twin rooms: each group is one
    # room), where more edges are no evidence at all; the robot stays out of the team frame
    # (safety property: a frame resting on a single aliased group is not merged)
    align_tie_min_places: int = 2
    """``consensus`` only between hypotheses that each rest on this many places or more."""
    # a frame on one place cannot be told from a twin room's alias, so adopting it is a risk (a
    # robot aligned on one room can sit in its twin, and pull a second robot there); keeping such
    # robots out instead loses every robot whose overlap with the team is one room. The default
    # adopts, reports the frame as unsettled (peers do not align through it), and leaves the
    # maps, the drift check and the safety net to catch an alias
    align_lone_place: bool = True
    """One group from a single place and no competitor: true adopts it once no more edges can arrive;
    false keeps the robot out of the team frame until a second place agrees."""
    # a lead in places is evidence for a frame but no proof against a rival: a row of identical
    # rooms lets the alias one room over rest on nearly as many places as the truth, and which
    # leads can turn on one more visit; the maps and landmarks compare the frames directly
    align_rivals: Literal["refuted", "lead"] = "refuted"
    """With the team map on: ``refuted`` adopts a frame only when the maps or the landmarks refute
    every rival hypothesis (else the robot stays out and a later epoch decides); ``lead`` adopts
    the clear leader in places, as without the team map."""
    place_radius: float = 2.0
    """Own closure poses closer than this are one place (m)."""
    # A correct frame leaves only residual misalignment, which the one-cell tolerance and the
    # column rule of alignment.map_check absorb (no conflict at all between robots' maps of the
    # simulator's floors in their true frames); a frame one room off moves whole walls: a
    # corridor's end wall alone is some forty cells, a room's walls and furniture hundreds.
    map_check: bool = True
    """Frame hypotheses face the robots' occupancy maps: one that puts the robot's walls into the
    team's clear free space, or the reverse, is refuted (docs/algorithms/pgo.md)."""
    map_conflict_ratio: float = 0.005
    """A refuting map disagrees on at least this fraction of the cells both maps know ..."""
    map_min_conflicts: int = 20
    """... and on at least this many coarse cells (some 1.8 m² of wall)."""
    map_coarse: float = 0.3
    """The grid the maps are compared on (m)."""
    map_occupancy: float = 1.0
    """|occupancy log-odds| above which a cell counts as occupied or free."""
    drift_check: bool = True
    """Safety: an estimate that bends away from the robot's own odometry beyond its drift model is not
    adopted; the robot falls back to its own frame."""
    drift_z: float = 4.0
    """The drift check's bound in drift-model sigmas."""
    drift_floor: float = 0.5
    """... plus this (m)."""
    # (measured: no faster on the benchmark graphs, worse on cubicle whose chordal relaxation is poor)
    distributed_init: bool = False
    """Chordal block Gauss–Seidel over the team before the block-coordinate descent."""
    init_rel_tol: float = 1e-3
    """An initialising robot is ready below this relative change."""
    init_max_rounds: int = 40
    """The leader starts the block-coordinate descent after this many initialisation rounds at most."""
    start_resend: int = 5
    """Rounds the leader repeats ``start`` (message loss)."""


def team_params(**overrides: Any) -> PgoParams:
    """The PGO of a SLAM team's agents: robust, with 600 rounds per epoch, no μ₀ floor."""
    return dataclasses.replace(PgoParams(robust=True, max_rounds=600, gnc_mu0_min=0.0), **overrides)
