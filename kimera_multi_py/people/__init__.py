"""People: the dynamic agents of the scene graph's Layer 2 (docs/algorithms/people.md).

- :mod:`.detection` -- each keyframe's points of a dynamic class grouped into person detections
  (centroid, extent, count), size-gated, bad ones dropped and counted;
- :mod:`.tracking` -- one robot's tracks: a constant-velocity Kalman filter per person, gating and
  Hungarian assignment, birth after confirmation, death after going unseen, every sample anchored
  in a submap so that PGO corrections move it;
- :mod:`.fusion` -- the team's tracks fused: tracks of two robots that follow the same person at the
  same time become one person with one id, the same on every robot that holds the same tables.
"""

from kimera_multi_py.people.detection import PersonDetections, detect_people
from kimera_multi_py.people.tracking import PeopleParams, PeopleTracker

__all__ = ["PeopleParams", "PeopleTracker", "PersonDetections", "detect_people"]
