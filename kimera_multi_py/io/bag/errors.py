"""Errors a user can act on: one line naming the bag's topic and what is wrong (docs/bags.md)."""

from __future__ import annotations

from kimera_multi_py.core.errors import DatasetError


class BagError(DatasetError):
    """A bag cannot feed a robot: ``topic`` names where, ``problem`` what."""

    def __init__(self, bag: str, topic: str, problem: str) -> None:
        self.bag, self.topic, self.problem = bag, topic, problem
        super().__init__(f"{bag}: {topic}: {problem}" if topic else f"{bag}: {problem}")
