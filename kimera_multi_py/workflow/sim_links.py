"""The simulation's budgeted links: what the runner needs to run a link budget on its clock
(docs/deployment.md, "Link budget").

:class:`SimLinks` holds the budget and the loopback network it runs on, says whether a waiting
PGO round waits on for a transfer under way or times out, records when every team map became
whole after the streams' end, and writes ``results.json["link_budget"]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.comms.link_budget import LinkBudget
from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.server.node import ServerNode

ROUND_WAIT_S = 5.0  # sim seconds a waiting PGO round lets the links run (a round timeout's worth)
DRAIN_S = 300.0  # sim seconds after the streams' end the team may take to finish under a budget


def _round_of(node: AgentNode | ServerNode) -> int:
    """The PGO round a node waits in (-1: none)."""
    session = getattr(getattr(node, "pgo", None), "session", None)
    return int(session.rnd) if session is not None else -1


class SimLinks:
    """A run's link budget on the simulated clock (``budget`` None: no budget, and every method
    a no-op but :meth:`note_complete`)."""

    def __init__(self, budget: LinkBudget | None) -> None:
        self.budget = budget
        self.net: LoopbackNetwork | None = None
        self.streams_end: float | None = None
        self.complete_at: float | None = None  # when every team map last became whole after the streams' end
        self._wait: tuple[float, tuple[tuple[int, int], ...]] | None = None  # a round's wait: since, rounds

    @property
    def active(self) -> bool:
        return self.budget is not None and self.net is not None

    def next_delivery(self) -> float | None:
        return self.net.next_delivery() if self.active and self.net is not None else None

    def pump(self) -> int:
        return self.net.pump() if self.active and self.net is not None else 0

    def round_waits(self, now: float, blocked: Sequence[AgentNode | ServerNode]) -> bool:
        """Do the waiting PGO rounds wait on (rather than time out)? While a transfer that ends
        within :data:`ROUND_WAIT_S` of the wait's start is under way; a round whose links are idle
        can get nothing more."""
        if not self.active:
            return False
        rounds = tuple((n.robot, _round_of(n)) for n in blocked)
        if self._wait is None or self._wait[1] != rounds:
            self._wait = (now, rounds)
        nxt = self.next_delivery()
        return nxt is not None and nxt <= self._wait[0] + ROUND_WAIT_S

    def end_wait(self) -> None:
        self._wait = None

    def note_complete(self, now: float, nodes: Sequence[AgentNode | ServerNode]) -> bool:
        """After the streams' end: is every robot's team map whole (no gap against any robot's
        version summary, exact mode) with nothing left on the links? Records when that began."""
        live = [n for n in nodes if isinstance(n, AgentNode) and n.maps is not None]
        team = {n.robot for n in live}
        whole = all(n.complete for n in nodes) and self.next_delivery() is None and all(
            not n.maps.gaps(team) for n in live if n.maps is not None and n.maps.mode == "exact")
        if not whole:
            self.complete_at = None
        elif self.complete_at is None:
            self.complete_at = now
        return whole

    def results(self) -> dict[str, Any]:
        """``results.json["link_budget"]``: the budget, each link's figures (bytes, queue delay, what
        could not be sent), and the seconds from the streams' end until every team map was whole."""
        b = self.budget
        out: dict[str, Any] = {"kbps": b.kbps if b is not None else None, "policy": b.policy if b is not None else None}
        if self.active and self.net is not None:
            links = self.net.link_report()
            out["links"] = links
            out["dropped_messages"] = sum(int(v["dropped_messages"]) for v in links.values())  # type: ignore[call-overload]
            out["queued_messages_at_end"] = sum(int(v["queued_messages"]) for v in links.values())  # type: ignore[call-overload]
            out["queue_delay_max_s"] = max((float(v["queue_delay_max_s"]) for v in links.values()),  # type: ignore[arg-type]
                                           default=0.0)
        end = self.streams_end
        out["streams_end_s"] = end
        out["team_maps_complete_s"] = self.complete_at - end if end is not None and self.complete_at is not None \
            else None
        return out
