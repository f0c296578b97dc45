"""Every robot, server and observer id and every id limit, in one place (docs/architecture.md).

Robot ``i`` owns the gtsam ``Symbol`` letter ``chr(ord('a') + i)`` for its pose keys (and the
scene graph's agent-node category), so a team has at most :data:`MAX_ROBOTS` robots, ids
``0..MAX_AGENT_ID``. Processes that are not robots use ids above that: the centralised server
(:data:`SERVER_ID`) and the launcher's silent observer (:data:`OBSERVER_ID`). A message on the wire
may carry any sender id up to :data:`MAX_ROBOT_ID` (the codec's bound, wider than the team's).
"""

from __future__ import annotations

MAX_ROBOTS = 26
"""Robots in a team at most: one Symbol letter ``a..z`` each."""
MAX_AGENT_ID = MAX_ROBOTS - 1
"""The highest robot id (25)."""
SERVER_ID = 999
"""The centralised server's id on the bus."""
OBSERVER_ID = 998
"""The id of ``kimera-multi launch``'s observer, which watches the team without joining it."""
MAX_ROBOT_ID = 4095
"""The highest sender id a message on the wire may carry (agents, server, observer, tools)."""
