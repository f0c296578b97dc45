"""AgentNode: the asyncio runtime that binds a pure :class:`Agent` to a Bus.

It announces the robot's presence, serves its keyframe constellations on
``kmp/{team}/r{robot}/keyframe/{id}``, subscribes to the team's topics, hands every message to
the agent and sends what the agent returns: ``LoopClosureRequest`` becomes a Bus query to the
target robot (the reply goes back into the agent), everything else is published on its topic.
A message the agent refuses (unknown robot, inconsistent content) is logged and counted; the
node keeps running.

Two ways to drive it: :meth:`drain` handles everything queued now (the single-process
simulation steps all nodes deterministically this way), :meth:`run` loops until closed (one
robot per process). :meth:`checkpoint` / :meth:`restore` pickle the agent's state.
"""

from __future__ import annotations

import asyncio
import logging
import pickle
from collections import Counter
from pathlib import Path

from kimera_multi_py.agent.agent import Agent, KeyframeInput
from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.comms.messages import LoopClosureReply, LoopClosureRequest, Message
from kimera_multi_py.errors import KimeraMultiError

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1


class AgentNode:
    """One robot on a Bus (see the module docstring)."""

    def __init__(self, agent: Agent, bus: Bus, query_timeout: float = 2.0) -> None:
        self.agent = agent
        self.bus = bus
        self.query_timeout = query_timeout
        self.errors: Counter[str] = Counter()
        self._sub = None
        self._serve = None

    @property
    def robot(self) -> int:
        return self.agent.robot

    async def start(self) -> None:
        await self.bus.announce()
        self._serve = await self.bus.serve(keys.keyframe_key(self.bus.team, self.robot, "*"), self._serve_keyframe)
        self._sub = self.bus.subscribe(keys.team_all(self.bus.team))

    def _serve_keyframe(self, key: str, request: Message | None) -> LoopClosureReply:
        keyframe = int(key.rsplit("/", 1)[-1])
        rid = request.request_id if isinstance(request, LoopClosureRequest) else 0
        return self.agent.serve_keyframe(keyframe, rid)

    async def process_keyframe(self, kf: KeyframeInput) -> None:
        await self.send(self.agent.process_keyframe(kf))

    async def send(self, msgs: list[Message]) -> None:
        for msg in msgs:
            if isinstance(msg, LoopClosureRequest):
                key = keys.keyframe_key(self.bus.team, msg.target, msg.keyframe)
                try:
                    replies = await self.bus.query(key, msg, timeout=self.query_timeout)
                except (KimeraMultiError, TimeoutError) as exc:
                    self._refuse("query", exc)
                    continue
                for reply in replies:
                    await self.send(self._handle(reply))
            else:
                await self.bus.publish(self.bus.key(msg.TOPIC), msg)

    def _handle(self, msg: Message) -> list[Message]:
        try:
            return self.agent.handle(msg)
        except (KimeraMultiError, ValueError, KeyError) as exc:
            self._refuse(type(msg).__name__, exc)
            return []

    def _refuse(self, what: str, exc: Exception) -> None:
        self.errors[what] += 1
        log.warning("robot %d refused %s: %s", self.robot, what, exc, extra={"robot": self.robot})

    async def drain(self) -> int:
        """Handle every message queued now; return how many."""
        assert self._sub is not None, "start() first"
        n = 0
        while (msg := self._sub.try_recv()) is not None:
            await self.send(self._handle(msg))
            n += 1
        return n

    async def run(self) -> None:
        """Handle messages until the subscription closes (one robot per process)."""
        assert self._sub is not None, "start() first"
        async for msg in self._sub:
            await self.send(self._handle(msg))
            await asyncio.sleep(0)

    async def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
        if self._serve is not None:
            self._serve.close()

    def checkpoint(self, path: str | Path) -> None:
        """Write the agent's whole state (atomically)."""
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        with tmp.open("wb") as fh:
            pickle.dump({"version": CHECKPOINT_VERSION, "agent": self.agent}, fh, protocol=pickle.HIGHEST_PROTOCOL)
        tmp.replace(path)

    @staticmethod
    def restore(path: str | Path) -> Agent:
        """Read an agent written by :meth:`checkpoint`; a bad file raises KimeraMultiError."""
        try:
            with Path(path).open("rb") as fh:
                data = pickle.load(fh)
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ValueError) as exc:
            raise KimeraMultiError(f"{path}: unreadable checkpoint: {exc}") from None
        if not isinstance(data, dict) or data.get("version") != CHECKPOINT_VERSION or not isinstance(
                data.get("agent"), Agent):
            raise KimeraMultiError(f"{path}: not a kimera-multi checkpoint of version {CHECKPOINT_VERSION}")
        return data["agent"]
