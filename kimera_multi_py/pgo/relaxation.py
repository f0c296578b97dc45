"""Step-size control of one block-SOR robot (docs/algorithms/pgo.md): the adaptive
over-relaxation factor ``ω`` with its back-off, the Nesterov momentum of the ``acceleration``
alternative with its restart, and the SE(3) extrapolation both use."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms.messages.pgo import PgoStatus
from kimera_multi_py.core.geometry import so3_exp, so3_log
from kimera_multi_py.pgo.params import PgoParams

OMEGA_WINDOW = 12  # block updates over which a growing step backs over-relaxation off


class Relaxation:
    """The step-size part of :class:`.agent.PgoAgent`: ``ω`` and the momentum of its updates."""

    def __init__(self, params: PgoParams) -> None:
        self.params = params
        self.omega = 1.0
        self.last_step = 0.0
        self.step_ratios: list[float] = []
        self.recent_steps: list[float] = []  # block steps since the last weight update (divergence check)
        self.gamma = 1.0  # Nesterov's momentum coefficient (``acceleration``)
        self.last_team_cost = np.inf

    def factor(self, step: float, updates_since_weights: int) -> float:
        """The over-relaxation factor for an update whose exact block step is ``step`` long
        (``updates_since_weights``: the robot's updates since the last weight change).

        Adaptive (Hageman & Young): the ratio ``λ`` of successive exact block steps estimates
        the iteration's contraction; at ``ω = 1`` it is ``ρ_GS = ρ_J²``, above it
        ``ρ_J² = (λ + ω − 1)² / (λω²)`` while ``λ > ω − 1``; then ``ω ← 2 / (1 + √(1 − ρ_J²))``
        (only upwards; a rejected relaxed step halves ``ω − 1``, :meth:`back_off`). A step more
        than twice the one ``OMEGA_WINDOW`` updates before it means ``ω`` belongs to a problem that
        has changed (a peer that was held and now moves): ``ω − 1`` halves, and ``ω`` adapts again
        (faults, 20 % loss: robot 2 at ``ω`` 1.93 diverged to a 1 m team error once the root
        joined in). The window is long because over-relaxed steps oscillate (modulus ``ω − 1``)
        from one update to the next.
        """
        p = self.params
        if p.acceleration:
            return 1.0  # momentum on top of over-relaxation diverges (measured on tinyGrid3D)
        if p.over_relaxation is not None:
            return p.over_relaxation
        if self.last_step > 0 and updates_since_weights > 1:
            self.step_ratios.append(step / self.last_step)
        self.last_step = step
        self.recent_steps = self.recent_steps[-OMEGA_WINDOW:] + [step] if updates_since_weights > 1 else []
        if len(self.recent_steps) > OMEGA_WINDOW and step > 2.0 * self.recent_steps[0] and self.omega > 1.0:
            self.omega = 1.0 + 0.5 * (self.omega - 1.0)
            self.step_ratios.clear()
            self.recent_steps.clear()
            return self.omega
        if len(self.step_ratios) >= 3:
            lam = float(np.median(self.step_ratios[-3:]))
            w = self.omega
            rho_j2 = None
            if lam < 1.0 and w == 1.0:
                rho_j2 = lam
            elif lam < 1.0 and lam > w - 1.0:
                rho_j2 = (lam + w - 1.0) ** 2 / (lam * w * w)
            if rho_j2 is not None and rho_j2 < 1.0:
                new_w = min(2.0 / (1.0 + np.sqrt(1.0 - rho_j2)), p.max_over_relaxation)
                if new_w > w + 1e-3:
                    self.omega = new_w
                    self.step_ratios.clear()
        return self.omega

    def back_off(self) -> None:
        """A relaxed step did not lower the block's cost: halve ``ω − 1`` and measure anew."""
        self.omega = 1.0 + 0.5 * (self.omega - 1.0)
        self.step_ratios.clear()

    def momentum(self, new: np.ndarray, old: np.ndarray, updates: int, cost: float,
                 statuses: dict[int, PgoStatus], team: tuple[int, ...], robot: int) -> np.ndarray:
        """What neighbours see after an update from ``old`` to ``new``: ``new`` itself, or with
        ``acceleration`` Nesterov's extrapolation, restarted on a team cost rise (the robot's
        ``cost`` plus the others' in ``statuses``) or every ``restart_interval`` ``updates``."""
        if self.params.acceleration and self._should_restart(updates, cost, statuses, team, robot):
            self.gamma = 1.0
        if self.params.acceleration:
            gamma_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * self.gamma**2))
            beta = (self.gamma - 1.0) / gamma_next
            self.gamma = gamma_next
            return extrapolate(new, old, beta)
        return new

    def restart(self, team_cost: bool = False) -> None:
        """Drop the momentum (the problem changed); ``team_cost`` also forgets the team cost."""
        self.gamma = 1.0
        if team_cost:
            self.last_team_cost = np.inf

    def _should_restart(self, updates: int, cost: float, statuses: dict[int, PgoStatus],
                        team: tuple[int, ...], robot: int) -> bool:
        if updates % self.params.restart_interval == 0:
            return True
        if len(statuses) < len(team) - 1:
            return False
        team_cost = cost + sum(s.cost for r, s in statuses.items() if r != robot)
        rise = team_cost > self.last_team_cost
        self.last_team_cost = team_cost
        return bool(rise)


def extrapolate(new: np.ndarray, old: np.ndarray, beta: float) -> np.ndarray:
    """``new ⊕ β·(new ⊖ old)`` per pose (rotation on the right, translation added):
    Nesterov extrapolation on SE(3) with the decoupled retraction."""
    if beta <= 0:
        return new
    rot = so3_log(np.swapaxes(old[:, :3, :3], 1, 2) @ new[:, :3, :3])
    out = new.copy()
    out[:, :3, :3] = new[:, :3, :3] @ so3_exp(beta * rot)
    out[:, :3, 3] = new[:, :3, 3] + beta * (new[:, :3, 3] - old[:, :3, 3])
    return out
