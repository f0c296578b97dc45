"""The knobs of one robot's front end, map and pose graph (docs/architecture.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.frontend.pcm import PcmNoise
from kimera_multi_py.mapping.config import MappingConfig


@dataclass
class AgentParams:
    """Knobs of the per-robot front end (defaults tuned on ``sims/office.toml``)."""

    mapping: MappingConfig = field(default_factory=MappingConfig)
    odom_sigmas: tuple[float, float] = (np.deg2rad(0.5), 0.03)  # rot (rad), trans (m) per keyframe
    closure_sigmas: tuple[float, float] = (0.05, 0.15)
    keyframe_distance: float = 0.5  # nominal, for PCM's drift model
    descriptor_every: int = 2
    descriptor_window: int = 8
    min_objects: int = 5
    min_similarity: float = 0.75
    # verification requests per peer per budget period. It binds: at 12, aliased_wing with 3 robots
    # (seed 9) dropped 255 of 405 inter-robot verification requests in the order they came, so which places got
    # verified hinged on timing; at 36 both modes verify about twice the true closures (team ATE
    # 0.030 → 0.024 m distributed), for 2.1x the bytes of fetched constellations (2x all bytes)
    budget: int = 36
    matches_per_query: int = 2
    distinct_places: int = 20  # keyframes between two places tried for one query
    budget_period: float = 20.0  # s
    verify_eps: float = 0.3
    min_inliers: int = 5
    closure_votes: bool = True  # closures sharing a keyframe and a robot split one vote in the robust cost
    pcm_min_size: int = 2
    pcm_groups: int = 3  # consistent groups per robot pair handed to the back end (see consensus.pcm)
    intra_min_gap: int = 40  # keyframes between an intra-robot closure's ends
    cloud_voxel: float = 0.2  # downsampling of the semantic cloud kept per keyframe for ICP
    icp_min_overlap: float = 0.1
    icp_max_correction: tuple[float, float] = (0.5, np.deg2rad(10.0))  # larger refinements are not trusted
    # a closure the scan registration does not confirm is rejected: the object constellation alone
    # is weak in roll and pitch (centroids sit at nearly one height; measured: 12-14 degrees off)
    require_registration: bool = True
    closure_correspondence: tuple[float, ...] = (0.6, 0.3, 0.15)  # GICP stages refining a closure (m)
    revisit_radius: float = 1.0  # intra-robot closures by place: older keyframes this close (m), 0 = off
    revisit_angle: float = np.deg2rad(45.0)  # ... and facing within this angle
    revisit_overlap: float = 0.4  # fraction of the cloud within the last correspondence distance
    # scan-to-map odometry (registration of each scan to the last reg_window keyframes' scans)
    registration: bool = True
    # how registration enters the pose graph: "fused", one factor per step, the odometry fused
    # with the registration (the registration in its well-constrained directions) under the
    # odometry's information — the same factor the centralised server receives, so both modes
    # solve one problem; "separate", the odometry factor plus a registration factor with the
    # information of GICP's Hessian (over-confident: GICP treats correlated point errors as
    # independent, so loop closures barely bend the chain; measured worse on office and small)
    registration_factor: str = "fused"
    reg_window: int = 8
    reg_voxel: float = 0.1
    # GICP stages (m); None: from the odometry's noise (registration_stages)
    reg_correspondence: tuple[float, ...] | None = None
    reg_point_sigma: float = 0.02  # per-point noise along a surface (m)
    reg_information_scale: float = 1.0  # discount of the GICP Hessian for correlated points
    reg_min_ratio: float = 1.0  # directions with less information than the odometry's are dropped
    reg_gate: float = 25.0  # squared Mahalanobis distance to the odometry beyond which it is not used
    # the floor seen at each keyframe sets the registration chain's roll, pitch and height
    # (mapping.floor: a ground robot on one floor; a fit off the predicted floor is not used)
    floor_reference: bool = True
    # the walls' grid seen at each keyframe sets the chain's yaw (mapping.heading: walls along two
    # perpendicular directions; a keyframe whose walls are off that grid is not used)
    heading_reference: bool = True
    team_object_sightings: int = 5  # sightings before a landmark enters the team's object map
    server: int | None = None  # centralised mode: the server's id (odometry streams to it)
    pcm: PcmNoise | None = None  # default: drift from odom_sigmas, closure noise from closure_sigmas

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
