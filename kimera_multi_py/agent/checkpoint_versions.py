"""What checkpoints of earlier format versions need to load (docs/deployment.md): the format
version, the versions still read, fields and classes added or renamed since, and the upgrade of
an agent restored from an older version."""

from __future__ import annotations

from typing import Any

import numpy as np

FORMAT_VERSION = 9
# 6: before people were tracked (loads with an empty tracker); 7: map tree kept current; 8: every
# submap's rows dense
READABLE_VERSIONS = (6, 7, 8, 9)
ADDED_FIELDS: dict[str, tuple[str, ...]] = {
    "kimera_multi_py.agent.params.AgentParams": ("people", "max_view_angle"),
    "kimera_multi_py.agent.closures.LoopClosureStats": ("rejected_view_angle",),
}

# Classes that moved when the package was split by concern (and when its largest modules were
# split by concept): files written before still load.
RENAMED_CLASSES: dict[str, str] = {
    "kimera_multi_py.agent.agent.AgentParams": "kimera_multi_py.agent.params.AgentParams",
    "kimera_multi_py.agent.loop_closure.DescriptorSpec": "kimera_multi_py.frontend.loop_closure.DescriptorSpec",
    "kimera_multi_py.consensus.pcm.PcmNoise": "kimera_multi_py.frontend.pcm.PcmNoise",
    "kimera_multi_py.consensus.pgo.LocalGraph": "kimera_multi_py.pgo.local_graph.LocalGraph",
    "kimera_multi_py.consensus.pgo.PgoParams": "kimera_multi_py.pgo.params.PgoParams",
    "kimera_multi_py.consensus.pgo_params.PgoParams": "kimera_multi_py.pgo.params.PgoParams",
    "kimera_multi_py.agent.agent.Closure": "kimera_multi_py.agent.closures.Closure",
    "kimera_multi_py.agent.agent.Constellation": "kimera_multi_py.agent.closures.Constellation",
    "kimera_multi_py.agent.agent.LoopClosureStats": "kimera_multi_py.agent.closures.LoopClosureStats",
    "kimera_multi_py.mapping.objects.Landmark": "kimera_multi_py.mapping.landmark.Landmark",
    "kimera_multi_py.mapping.semantic_octree.ObservationModel": "kimera_multi_py.mapping.observation.ObservationModel",
    "kimera_multi_py.mapping.semantic_octree._Block": "kimera_multi_py.mapping.octree_block.OctreeBlock",
}
# Attributes renamed since version 6 (per class): files written before still load.
RENAMED_ATTRIBUTES: dict[str, dict[str, str]] = {
    "kimera_multi_py.mapping.submaps.SubmapMap": {"octree": "_tree"},  # version 8: the tree became a lazy view
}


def upgrade(agent: Any, version: int) -> None:
    """Bring an agent restored from a checkpoint of ``version`` to the current state's shape."""
    if version < 7:
        _add_people(agent)
    if version < 8:  # the tree was kept current (nothing pending), and submap rows were int32
        agent.map._pending = []
        for s in agent.map.submaps.values():
            s.rows = s.rows.astype(np.int16)
    if version < 9:  # submaps that take no more scans hold their rows as a palette
        ids = agent.map.submap_ids()
        for sid in ids[:-1]:
            agent.map.submaps[sid].compact()


def _add_people(agent: Any) -> None:
    """A version-6 agent tracked no people: give it an empty tracker (default knobs) that knows its
    submaps."""
    from kimera_multi_py.people.tracking import PeopleTracker

    agent.people = PeopleTracker(agent.map.template.dynamic_classes, agent.params.people)
    for sid in agent.map.submap_ids():
        agent.people.set_submap_pose(sid, agent.map.submaps[sid].T)
