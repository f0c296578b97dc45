"""The per-robot front end's knobs (:class:`AgentParams`), the ``agent`` section of the configuration
(docs/architecture.md). Every field's docstring is its description in ``kimera-multi config --dump``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from kimera_multi_py.frontend.pcm import PcmNoise
from kimera_multi_py.mapping.config import MappingConfig
from kimera_multi_py.people.tracking import PeopleParams


@dataclass
class AgentParams:
    """Knobs of the per-robot front end (defaults tuned on ``sims/office.toml``)."""

    mapping: MappingConfig = field(default_factory=MappingConfig)
    """The robot's maps (octree, objects, submaps): the ``mapping`` section of the configuration."""
    people: PeopleParams = field(default_factory=PeopleParams)
    """Person detection and tracking (docs/algorithms/people.md); the library's defaults."""
    odom_sigmas: tuple[float, float] = (np.deg2rad(0.5), 0.03)
    """Odometry noise per keyframe: rotation (rad), translation (m). Runs set it from their keyframe
    source's noise model (the scenario's ``[odometry]``, a recording's manifest) unless given."""
    closure_sigmas: tuple[float, float] = (0.05, 0.15)
    """Loop-closure noise: rotation (rad), translation (m)."""
    keyframe_distance: float = 0.5
    """Nominal distance between keyframes (m), for PCM's drift model; set like ``odom_sigmas``."""
    descriptor_every: int = 2
    """Keyframes between two published place descriptors."""
    descriptor_window: int = 8
    """Keyframes whose objects form one constellation."""
    min_objects: int = 5
    """Objects a constellation needs to be described."""
    min_similarity: float = 0.75
    """Descriptor similarity from which a peer's place is a loop-closure candidate."""
    # It binds: at 12, aliased_wing with 3 robots (seed 9) dropped 255 of 405 inter-robot
    # verification requests in the order they came, so which places got verified hinged on timing;
    # at 36 both modes verify about twice the true closures (team ATE 0.030 → 0.024 m distributed),
    # for 2.1x the bytes of fetched constellations (2x all bytes)
    budget: int = 36
    """Verification requests per peer per budget period."""
    matches_per_query: int = 2
    """Own places tried per peer descriptor (the most similar first)."""
    distinct_places: int = 20
    """Keyframes between two places tried for one query."""
    budget_period: float = 20.0
    """Length of the verification budget's period (s)."""
    verify_eps: float = 0.3
    """Geometric verification: tolerance on the pairwise distances of matched objects (m)."""
    min_inliers: int = 5
    """Geometric verification: object matches a closure needs."""
    closure_votes: bool = True
    """Closures sharing a keyframe and a robot split one vote in the robust cost."""
    pcm_min_size: int = 2
    """Smallest consistent set PCM accepts."""
    pcm_groups: int = 3
    """Consistent groups per robot pair handed to the back end (see frontend.pcm)."""
    intra_min_gap: int = 40
    """Keyframes between the two ends of an intra-robot closure at least."""
    cloud_voxel: float = 0.2
    """Downsampling of the semantic cloud kept per keyframe for ICP (m)."""
    icp_min_overlap: float = 0.1
    """Overlap of the clouds a closure's scan registration needs to confirm it (fraction)."""
    icp_max_correction: tuple[float, float] = (0.5, np.deg2rad(10.0))
    """Largest refinement of a closure ICP may make: translation (m), rotation (rad); larger is not trusted."""
    # the object constellation alone is weak in roll and pitch (centroids sit at nearly one
    # height; measured: 12-14 degrees off)
    require_registration: bool = True
    """Reject a closure the scan registration does not confirm."""
    # two views facing apart see opposite faces of the same furniture, and the registration pairs
    # a front face with a back face: measured on generated buildings, closures between views over
    # 135 degrees apart were off by about the objects' depth (0.2-0.6 m) along the view axis
    # (docs/algorithms/frontend.md, "Views facing apart")
    max_view_angle: float = np.deg2rad(90.0)
    """Largest angle between the two keyframes' forward axes a closure may join (rad); pi: no limit."""
    closure_correspondence: tuple[float, ...] = (0.6, 0.3, 0.15)
    """GICP stages refining a closure: correspondence distances (m)."""
    revisit_radius: float = 1.0
    """Intra-robot closures by place: older keyframes this close by odometry (m); 0 turns them off."""
    revisit_angle: float = np.deg2rad(45.0)
    """... and facing within this angle (rad)."""
    revisit_overlap: float = 0.4
    """... and this fraction of the cloud within the last correspondence distance."""
    registration: bool = True
    """Scan-to-map odometry: register each scan to the last ``reg_window`` keyframes' scans."""
    # "fused": the odometry fused with the registration (in its well-constrained directions) under
    # the odometry's information, the same factor the centralised server receives, so both modes
    # solve one problem; "separate": the odometry factor plus a registration factor with the
    # information of GICP's Hessian (over-confident: GICP treats correlated point errors as
    # independent, so loop closures barely bend the chain; measured worse on office and small)
    registration_factor: Literal["fused", "separate"] = "fused"
    """How registration enters the pose graph: ``fused`` (one factor per step) or ``separate``."""
    reg_window: int = 8
    """Keyframes whose scans a new scan is registered to."""
    reg_voxel: float = 0.1
    """Downsampling of the registration's scans (m)."""
    reg_correspondence: tuple[float, ...] | None = None
    """GICP stages of the scan odometry (m); null: from the odometry's noise (``registration_stages``)."""
    reg_point_sigma: float = 0.02
    """Per-point noise along a surface (m)."""
    reg_information_scale: float = 1.0
    """Discount of the GICP Hessian for correlated points."""
    reg_min_ratio: float = 1.0
    """Directions with less information than the odometry's are dropped (ratio)."""
    reg_gate: float = 25.0
    """Squared Mahalanobis distance to the odometry beyond which a registration is not used."""
    # mapping.floor: a ground robot on one floor; a fit off the predicted floor is not used
    floor_reference: bool = True
    """The floor seen at each keyframe sets the registration chain's roll, pitch and height."""
    # mapping.heading: walls along two perpendicular directions; a keyframe whose walls are off
    # that grid is not used
    heading_reference: bool = True
    """The walls' grid seen at each keyframe sets the registration chain's yaw."""
    team_object_sightings: int = 5
    """Sightings before a landmark enters the team's object map."""
    server: int | None = None
    """Centralised mode: the server's id (odometry streams to it). Set from the run's mode."""
    pcm: PcmNoise | None = None
    """PCM's noise model; null: drift from ``odom_sigmas``, closure noise from ``closure_sigmas``."""

    def registration_stages(self) -> tuple[float, ...]:
        """The scan odometry's correspondence distances: as given, or two stages from three sigma
        of the odometry's prediction error at a point 4 m away (rotation times range, plus the
        translation over three axes) down to half that. Wider than the prediction can be wrong
        only admits wrong correspondences: with (0.5, 0.2) m, 8 % of office's keyframes fell back
        to the odometry, with (0.15, 0.07) m 3 % (seeds 1 and 2, robots 0-2, 200 keyframes each)."""
        if self.reg_correspondence is not None:
            return self.reg_correspondence
        first = max(3.0 * (np.sqrt(3.0) * self.odom_sigmas[1] + 4.0 * self.odom_sigmas[0]), 0.1)
        return (float(first), float(first) / 2)

    def odom_information(self) -> np.ndarray:
        return np.diag(np.repeat(1.0 / np.square(self.odom_sigmas), 3))

    def pcm_noise(self) -> PcmNoise:
        """PCM's drift model: the per-keyframe odometry noise as a random walk per metre."""
        if self.pcm is not None:
            return self.pcm
        per_m = 1.0 / np.sqrt(self.keyframe_distance)
        return PcmNoise(closure_rot=self.closure_sigmas[0], closure_trans=self.closure_sigmas[1],
                        odom_rot_per_m=self.odom_sigmas[0] * per_m, odom_trans_per_m=self.odom_sigmas[1] * per_m)


@dataclass
class NodeParams:
    """The node's own knobs (the agent's and the solver's are separate)."""

    query_timeout: float = 2.0
    """Wall seconds a constellation query waits for its reply (in the simulation its wait ends when
    the reply can no longer arrive, on the simulated clock)."""
    state_period: float = 5.0
    """Clock seconds between AgentState messages (the tick's ``wall`` clock)."""
    resend_period: float = 5.0
    """Clock seconds between re-sends of unacknowledged closures."""
    server: int | None = None
    """Centralised mode: the server's id (then no team PGO). Set from the run's mode."""
    map_consensus: Literal["off", "roam", "exact", "laplacian"] = "exact"
    """Map consensus mode: off, roam, exact or laplacian (docs/algorithms/map_consensus.md)."""
    descriptor_repeats: int = 1
    """Lossy links: every descriptor goes out again with the next this many times (duplicates are ignored)."""
    query_retries: int = 2
    """Lossy links: a constellation query that gets no reply is asked again this many times."""
    query_reasks: int = 3
    """A query still unanswered after its retries is asked again, up to this many times, every
    ``resend_period`` while its target is present; and whenever the target (re)appears."""
    compact_wire: bool = True
    """Compact encodings: verification clouds at the closure registration's resolution, packed
    small; public poses as float32 deltas of the poses that moved (:mod:`kimera_multi_py.pgo.pose_stream`);
    map evidence as palette rows, the growing submap held between versions (map consensus
    ``palette_rows`` and ``hold``); closure batches against the acknowledged one
    (:mod:`kimera_multi_py.comms.closure_stream`); a fetched peer keyframe kept and fetched once;
    GNC weights when they change (``weights_full_every``); compressed envelopes
    (:mod:`kimera_multi_py.comms.wire`). False: the full-size formats (to measure what compaction saves)."""
    link_budget: float | None = None
    """kB/s per peer link, a token bucket in the bus with PGO and closure traffic first, then
    objects, then map evidence (docs/deployment.md, "Link budget"); null: unlimited."""
    link_policy: Literal["priority", "fifo"] = "priority"
    """Under a link budget: by priority class (the default) or first in, first out (a baseline)."""
