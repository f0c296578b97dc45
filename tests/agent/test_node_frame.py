"""The frame a node reports follows where its poses are: a robot kept out of the team
frame reports its own id as ``frame`` (and its map and objects go out in that frame), in both
modes, and gets the team frame back once it is admitted again."""

import asyncio
from types import SimpleNamespace

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode, NodeParams
from kimera_multi_py.agent.outputs import outcome_of
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms import LoopbackNetwork
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.core.geometry import yaw_pose
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.core.posegraph import robot_key
from kimera_multi_py.eval.team import excluded_robots
from kimera_multi_py.server.node import SERVER_ID

KEYFRAMES = 3


def keyframe(i: int, seed: int = 0) -> KeyframeInput:
    """A synthetic keyframe: 200 hits in a 6 m box around the robot, 0.5 m along x from the last."""
    rng = np.random.default_rng(1000 * seed + i)
    points = rng.uniform(-3.0, 3.0, (200, 3))
    return KeyframeInput(index=i, stamp=float(i), odometry=np.eye(4) if i == 0 else yaw_pose(0.5, 0.0, 0.0, 0.0),
                         points=points, labels=np.ones(200, int), hit=np.ones(200, bool), max_range=10.0)


async def started(robot: int, central: bool) -> AgentNode:
    net = LoopbackNetwork(team="t0", seed=0)
    server = SERVER_ID if central else None
    node = AgentNode(Agent(robot, None, AgentParams(server=server)), net.bus(robot), params=NodeParams(server=server))
    await node.start()
    for i in range(KEYFRAMES):
        await node.process_keyframe(keyframe(i, robot))
    return node


def server_poses(robot: int, settled: bool, x: float = 0.0, rnd: int = 1) -> PublicPoses:
    """The server's corrected poses of ``robot`` (``settled=False``: kept out, in its own frame)."""
    return PublicPoses(robot=SERVER_ID, round=rnd, keys=np.array([robot_key(robot, k) for k in range(KEYFRAMES)],
                                                                 dtype=np.int64),
                       poses=np.stack([yaw_pose(x + 0.5 * k, 1.0, 0.0, 0.0) for k in range(KEYFRAMES)]),
                       settled=settled)


def root_outcome() -> SimpleNamespace:
    return SimpleNamespace(robot=0, alignment={"status": "root", "frame": 0})


def test_centralised_node_kept_out_by_the_server_reports_its_own_frame_and_gets_the_team_frame_back():
    async def main() -> None:
        node = await started(1, central=True)
        node.agent.robot_graph.add((0, 1))  # robot 0 and robot 1 closed loops: one component
        assert node.alignment == {"frame": 1}  # no word from the server yet: its own frame
        # the server aligned it: the team frame (robot 0's)
        await node._dispatch(server_poses(1, settled=True))
        await node.tick(wall=0.0)
        assert node.frame == 0 and node.maps.frame == 0 and node.objects.frame == 0
        assert node.alignment == {"status": "aligned", "settled": True, "source": "server", "frame": 0}
        assert excluded_robots([root_outcome(), outcome_of(node)]) == []
        # a later solve keeps it out (not settled): its poses come back in its own frame, and so
        # does its map; the outcome says excluded, in frame 1
        await node._dispatch(server_poses(1, settled=False, x=7.0, rnd=2))
        await node.tick(wall=1.0)
        assert node.frame == 1 and node.maps.frame == 1 and node.objects.frame == 1
        np.testing.assert_allclose(node.agent.poses[0], yaw_pose(7.0, 1.0, 0.0, 0.0))  # the poses were applied
        out = outcome_of(node)
        assert out.alignment["status"] == "excluded" and out.alignment["frame"] == 1
        assert out.alignment["settled"] is False and "kept it out" in out.alignment["reason"]
        assert excluded_robots([root_outcome(), out]) == [1]
        # another robot's poses, kept out or not, say nothing about ours
        await node._dispatch(server_poses(0, settled=True, rnd=2))
        assert node.frame == 1 and node.server_settled is False
        # admitted again: the team frame back
        await node._dispatch(server_poses(1, settled=True, rnd=3))
        await node.tick(wall=2.0)
        assert node.frame == 0 and node.maps.frame == 0 and node.alignment["status"] == "aligned"
        assert excluded_robots([root_outcome(), outcome_of(node)]) == []
        assert not node.errors
        await node.close()

    asyncio.run(main())


def test_centralised_root_reports_root_and_a_robot_without_closures_stays_in_its_own_frame():
    async def main() -> None:
        root = await started(0, central=True)
        await root._dispatch(server_poses(0, settled=True))
        assert root.alignment == {"status": "root", "settled": True, "source": "server", "frame": 0}
        lone = await started(2, central=True)  # no closure with anyone: the server keeps it out
        await lone._dispatch(server_poses(2, settled=False))
        assert lone.frame == 2 and lone.alignment["status"] == "excluded"
        for n in (root, lone):
            await n.close()

    asyncio.run(main())


class EpochsPgo:
    """Stands in for the node's TeamPgo: each tick completes the next of ``epochs`` (the solver
    of the epoch, as ``TeamPgo.last_pgo``)."""

    def __init__(self, epochs: list[SimpleNamespace]) -> None:
        self.epochs = list(epochs)
        self.completed = 0
        self.last_pgo: SimpleNamespace | None = None
        self.final_done = False
        self.busy = False
        self.stats = SimpleNamespace(rounds=0, epochs=0)

    def tick(self, *args: object) -> list:
        if self.epochs:
            self.last_pgo = self.epochs.pop(0)
            self.completed += 1
            self.stats.epochs += 1
        return []

    def handle(self, *args: object) -> None:
        pass

    def blocked(self) -> bool:
        return False


def epoch(status: str, aligned: bool, excluded: bool, pairs: list[tuple[int, int]]) -> SimpleNamespace:
    """An epoch's solver as the node reads it (no edges: the outcome's closure weights are empty)."""
    none = np.zeros(0, int)
    local = SimpleNamespace(robot_graph=pairs, inter_own=none, intra_odometry=np.zeros(0, bool))
    frame = SimpleNamespace(aligned=aligned, excluded=excluded, alignment={"status": status, "settled": False})
    return SimpleNamespace(frame=frame, local=local)


def test_distributed_node_excluded_in_the_last_epoch_reports_its_own_frame_until_it_is_aligned_again():
    async def main() -> None:
        node = await started(2, central=False)
        # epoch 1 aligns it through robot 1 (robot 1 through robot 0): the team frame, robot 0's;
        # epoch 2 keeps it out (its drift check: still ``aligned``, but ``excluded``); epoch 3 aligns it again
        node.pgo = EpochsPgo([epoch("aligned", True, False, [(0, 1), (1, 2)]),
                              epoch("excluded", True, True, [(0, 1), (1, 2)]),
                              epoch("aligned", True, False, [(0, 1), (1, 2)])])
        frames, maps, statuses = [], [], []
        for t in range(3):
            await node.tick(wall=float(t))
            frames.append(node.frame)
            maps.append(node.maps.frame)
            statuses.append((node.alignment["status"], node.alignment["frame"]))
        assert frames == maps == [0, 2, 0]
        assert statuses == [("aligned", 0), ("excluded", 2), ("aligned", 0)]
        await node.close()

    asyncio.run(main())


def test_distributed_node_excluded_in_a_later_epoch_is_reported_kept_out():
    async def main() -> None:
        node = await started(1, central=False)
        node.pgo = EpochsPgo([epoch("aligned", True, False, [(0, 1)]),
                              epoch("excluded", False, True, [(0, 1)])])
        await node.tick(wall=0.0)
        assert excluded_robots([root_outcome(), outcome_of(node)]) == []
        await node.tick(wall=1.0)
        out = outcome_of(node)
        assert out.alignment == {"status": "excluded", "settled": False, "frame": 1}
        assert excluded_robots([root_outcome(), out]) == [1]
        await node.close()

    asyncio.run(main())


def test_the_node_left_out_by_its_safety_net_after_the_final_epoch_is_no_longer_complete(monkeypatch) -> None:
    """The node's side: its safety net refutes the frame the final epoch left it in, so it asks
    for the final epoch again (its state says it is not complete) and waits for it."""
    async def main() -> None:
        node = await started(1, central=False)
        reopened: list[int] = []
        pgo = SimpleNamespace(last_pgo=SimpleNamespace(frame=SimpleNamespace()), completed=3, busy=False,
                              stats=SimpleNamespace(rounds=0), tick=lambda *a, **k: [], blocked=lambda: False,
                              reopen=lambda r: reopened.append(r) or True)
        node.pgo = pgo
        node.complete = True
        node._frame_check_at = 0.0
        monkeypatch.setattr(node, "_safety_net", lambda last: True)
        assert not node.settled
        await node.tick(wall=1.0)
        assert reopened == [1] and not node.complete and node._frame_check_at is None
        await node.close()

    asyncio.run(main())
