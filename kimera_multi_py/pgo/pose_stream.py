"""The public-pose stream: what a robot's neighbours hold of its public poses, in few bytes
(docs/algorithms/pgo.md, "Bytes on the wire").

The sender's :class:`PoseEncoder` turns each round's full :class:`PublicPoses` into

* the full message itself (a *keyframe*: float64, every key) on the first round, every
  ``full_every`` rounds, and whenever the keys or the ``settled`` flag change; but a keyframe
  that repeats an unchanged one (no delta went out against it) waits ``quiet_every`` rounds for
  the next, so every keyframe still goes out twice ``full_every`` rounds apart;
* otherwise a :class:`PoseDeltas` of only the poses that moved more than ``translation_tol`` /
  ``rotation_tol`` from what the receivers hold: float32 deltas against the keyframe;
* or nothing, when no pose moved that far.

Every delta is taken against the keyframe, not against the previous message, so a lost delta
costs only its own poses, until they move again or the next keyframe (at most ``full_every``
rounds) repairs them; a lost keyframe makes its deltas unusable until the next one. The sender
keeps exactly what a receiver reconstructs (the same float32 rounding), so without loss every
receiver holds every public pose within the tolerance of the sender's.

The receiver's :class:`PoseDecoder` turns what arrives back into full :class:`PublicPoses` (the
keyframe's keys, in its order, with the newest pose of each), so the solvers never see deltas.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import PoseDeltas, PublicPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp, so3_log


@dataclass(frozen=True)
class PoseStreamParams:
    """Knobs of the public-pose stream."""

    # below what the solver resolves: measured on smallGrid3D (5 robots) the gap to the
    # centralised optimum and the rounds are those of full messages (-7.8e-12, 50 rounds), while
    # 1e-4 m / 1e-5 rad already moves both (5.4e-10, 58 rounds) for 13 % fewer bytes
    translation_tol: float = 1e-6
    """A public pose is sent again once it moved this far (m) from what the receivers hold ..."""
    rotation_tol: float = 1e-7
    """... or turned this much (rad)."""
    full_every: int = 20
    """Rounds between keyframes (full float64 messages), the repair of lost messages."""
    quiet_every: int = 80
    """Rounds after a keyframe that repeats an unchanged one, while still no pose moves: a receiver
    of either copy holds the keyframe itself, and a further copy repairs only two lost ones."""


def _moved(held: np.ndarray, poses: np.ndarray, p: PoseStreamParams) -> np.ndarray:
    dt = np.linalg.norm(poses[:, :3, 3] - held[:, :3, 3], axis=1)
    # rotation angle of held^T R from the Frobenius norm: |R1 - R2|_F = 2 sqrt(2) sin(angle / 2)
    dr = np.linalg.norm(poses[:, :3, :3] - held[:, :3, :3], axis=(1, 2)) / np.sqrt(2.0)
    return (dt > p.translation_tol) | (dr > p.rotation_tol)


def _apply(base: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    d = np.asarray(deltas, dtype=np.float64)
    return base @ make_pose(so3_exp(d[:, :3]), d[:, 3:])


@dataclass
class _Keyframe:
    round: int
    keys: np.ndarray
    poses: np.ndarray  # the keyframe's poses
    held: np.ndarray  # what a receiver holds now
    stamp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # round of each held pose
    moved: bool = False  # a delta went out against it
    repeat: bool = False  # it repeats a keyframe against which no delta went out


class PoseEncoder:
    """One robot's outgoing public poses (see the module docstring)."""

    def __init__(self, params: PoseStreamParams | None = None) -> None:
        self.params = params or PoseStreamParams()
        self._key: _Keyframe | None = None
        self._settled = True

    def encode(self, msg: PublicPoses) -> Message | None:
        """What to send for ``msg``: itself, its :class:`PoseDeltas`, or None (nothing moved)."""
        k, p = self._key, self.params
        poses = np.asarray(msg.poses, dtype=np.float64)
        same = k is not None and msg.settled == self._settled and np.array_equal(msg.keys, k.keys)
        if k is None or not same or not 0 <= msg.round - k.round < (
                p.quiet_every if k.repeat and not k.moved else p.full_every):
            self._key = _Keyframe(msg.round, np.array(msg.keys), poses.copy(), poses.copy(),
                                  repeat=same and k is not None and not k.moved)
            self._settled = msg.settled
            return msg
        idx = np.flatnonzero(_moved(k.held, poses, p))
        if not len(idx):
            return None
        rel = inverse(k.poses[idx]) @ poses[idx]
        deltas = np.concatenate([so3_log(rel[:, :3, :3]), rel[:, :3, 3]], axis=1).astype(np.float32)
        k.held[idx] = _apply(k.poses[idx], deltas)
        k.moved = True
        return PoseDeltas(robot=msg.robot, round=msg.round, base=k.round, index=idx.astype(np.int32),
                          deltas=deltas, settled=msg.settled)


class PoseDecoder:
    """Every sender's public poses as this robot holds them (see the module docstring).

    ``unusable`` counts deltas whose keyframe this robot does not hold (lost, or not yet come).
    """

    def __init__(self) -> None:
        self._keys: dict[int, _Keyframe] = {}
        self.unusable = 0

    def decode(self, msg: Message) -> PublicPoses | None:
        """The full public poses ``msg`` brings (a :class:`PublicPoses` passes as it is, and becomes
        its sender's keyframe), or None for a delta against an unknown keyframe. Raises
        :class:`MessageError` for a delta that does not fit its keyframe."""
        if isinstance(msg, PublicPoses):  # the newest word, as without the stream (a restart re-keys)
            poses = np.array(msg.poses, dtype=np.float64)
            self._keys[msg.robot] = _Keyframe(msg.round, np.array(msg.keys), poses, poses.copy(),
                                              np.full(len(poses), msg.round, np.int64))
            return msg
        if not isinstance(msg, PoseDeltas):
            raise TypeError(f"pose stream: not a pose message: {type(msg).__name__}")
        k = self._keys.get(msg.robot)
        if k is None or k.round != msg.base:
            self.unusable += 1
            return None
        if len(msg.index) and int(msg.index.max()) >= len(k.keys):
            raise MessageError(f"PoseDeltas.index: {int(msg.index.max())} beyond the {len(k.keys)} keys "
                               f"of keyframe round {msg.base}")
        fresh = k.stamp[msg.index] < msg.round  # a delta overtaken by a newer one of the same pose
        idx = msg.index[fresh]
        k.held[idx] = _apply(k.poses[idx], msg.deltas[fresh])
        k.stamp[idx] = msg.round
        return PublicPoses(robot=msg.robot, round=msg.round, keys=k.keys, poses=k.held.copy(),
                           settled=msg.settled)
