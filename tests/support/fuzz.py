"""Fuzzed and mutated payloads for a robot's topics: what a stranger or a broken radio could send.

Pure and seeded: :func:`fuzz_payloads` returns ``(key, bytes)`` pairs on one robot's topics,
mostly mutations of valid envelopes of every message type (bit flips, overwrites, cuts,
growth, splices, noise, envelopes with one bad field), some valid messages as they stand, and
some valid messages on another robot's keys; :func:`stranger_traffic` is a second team's robot
publishing valid messages. Used by the fuzz test and ``benchmarks/faults.py``.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Awaitable, Callable
from typing import Any

import msgpack

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.base import Message
from tests.support.samples import all_random_messages

_BAD_VALUES: tuple[object, ...] = (None, -1, 2**63, "x" * 70, 1.5, float("nan"), [], {})
_BYTES = (0x00, 0xFF, 0x7F, 0x80, 0xC0, 0xC1, 0xD9, 0xDD, 0xDF, 0xCB)


def mutate(data: bytes, rng: random.Random, pool: list[bytes]) -> bytes:
    """One random mutation of ``data`` (``pool``: other payloads to splice with)."""
    b = bytearray(data)
    kind = rng.randrange(8)
    if kind == 0:  # flip a few bits
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
    elif kind == 1:  # overwrite bytes with msgpack-significant values
        for _ in range(rng.randint(1, 3)):
            b[rng.randrange(len(b))] = rng.choice(_BYTES)
    elif kind == 2:  # truncate
        b = b[: rng.randrange(len(b))]
    elif kind == 3:  # append garbage
        b += rng.randbytes(rng.randint(1, 64))
    elif kind == 4:  # splice two payloads
        other = rng.choice(pool)
        b = b[: rng.randrange(len(b) + 1)] + other[rng.randrange(len(other) + 1):]
    elif kind == 5:  # pure noise
        b = bytearray(rng.randbytes(rng.randint(0, 256)))
    elif kind == 6:  # a well-formed envelope with one bad field
        env = msgpack.unpackb(data, raw=False, strict_map_key=False)
        if isinstance(env, dict) and env:
            env[rng.choice(sorted(env))] = rng.choice(_BAD_VALUES)
        b = bytearray(msgpack.packb(env, use_bin_type=True, default=str))
    else:  # duplicate a slice in place
        i = rng.randrange(len(b))
        j = min(len(b), i + rng.randint(1, 32))
        b = b[:j] + b[i:j] + b[j:]
    return bytes(b)


def fuzz_payloads(team: str, robot: int, n: int, seed: int = 0, valid: float = 0.05,
                  wrong_owner: float = 0.03) -> list[tuple[str, bytes]]:
    """``n`` (key, payload) pairs on ``robot``'s topics of ``team``: a fraction ``valid`` left
    intact, a fraction ``wrong_owner`` intact but on robot ``robot + 1``'s key, the rest mutated."""
    rng = random.Random(seed)
    codec = Codec(team, robot)
    seeds = [(m.TOPIC, codec.encode(m)) for s in range(3) for m in all_random_messages(seed=s, robot=robot)]
    pool = [d for _, d in seeds]
    out = []
    for i in range(n):
        topic, data = seeds[i % len(seeds)]
        roll = rng.random()
        if roll < valid:
            out.append((keys.topic_key(team, robot, topic), data))
        elif roll < valid + wrong_owner:
            out.append((keys.topic_key(team, robot + 1, topic), data))
        else:
            out.append((keys.topic_key(team, robot, topic), mutate(data, rng, pool)))
    return out


__all__ = ["fuzz_payloads", "mutate"]


async def stranger_traffic(other: Any, target_team: str, wait: Callable[[Callable[[], bool], float], Awaitable[Any]],
                           seeds: int = 5) -> tuple[list[Message], Any]:
    """A robot of another team (``other``, a ZenohBus) publishes valid messages of every type on its
    own team's keys, and waits until its own subscriber (the witness, returned) has them all, which
    shows the traffic really flows; then it puts the same envelopes straight onto ``target_team``'s
    keys, as a misconfigured robot would. ``wait(predicate, timeout)`` waits for a condition.
    Returns the messages (sent twice each) and the witness subscription."""
    import zenoh

    witness = other.subscribe(keys.team_all(other.team))
    msgs = [m for s in range(seeds) for m in all_random_messages(seed=s, robot=other.robot)]
    await other.wait_for_subscribers(other.key(msgs[0].TOPIC), timeout=5)
    for m in msgs:
        await other.publish(other.key(m.TOPIC), m)
        await asyncio.sleep(0)
    await wait(lambda: witness.pending() >= len(msgs), 20)
    codec = Codec(other.team, other.robot)
    for m in msgs:
        other.session.put(keys.topic_key(target_team, other.robot, m.TOPIC), codec.encode(m),
                          congestion_control=zenoh.CongestionControl.BLOCK)
    return msgs, witness
