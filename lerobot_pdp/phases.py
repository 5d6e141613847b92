"""Which phase latent each env of a rollout is in, for policies with one latent per phase (paper Eq. 12).

Pick-place and kitchen demonstrations split into phases at gripper events (reach, then carry); the fitted
or steered latent is then one z per phase, and the rollout moves to the next one when the gripper command
flips. Tracked per batch element: in a vectorised rollout the envs grasp at different times, and one env's
grasp must not switch the others to their carry latent. A phase counts the gripper flips since the episode
began, whatever latent is active: a latent set mid-episode (live steering, a fit finishing) takes over at the
phase the robot is in, not back at its reach.
"""

from __future__ import annotations

import torch
from torch import Tensor


class PhaseTracker:
    """Per-env phase indices (gripper flips since the episode began), advanced when an env's gripper state
    flips and holds."""

    def __init__(self) -> None:
        self.phase: Tensor | None = None  # [B] current phase of each env
        self._closed: Tensor | None = None  # [B] gripper state of each env's current phase
        self._hold: Tensor | None = None  # [B] consecutive actions that disagree with it

    def reset(self) -> None:
        """Every env back to phase 0 (a new episode)."""
        self.phase = self._closed = self._hold = None

    def phases(self, batch_size: int, device: torch.device | str) -> Tensor:
        """Per-env phase indices [batch_size]; restarts at phase 0 when the batch size changes."""
        if self.phase is None or self.phase.shape[0] != batch_size:
            self.phase = torch.zeros(batch_size, dtype=torch.long, device=device)
            self._closed = None
        return self.phase

    def update(self, closed: Tensor, hold_steps: int) -> Tensor:
        """Record each env's executed gripper command (``closed`` [B] bool); returns which envs moved on [B].

        The first command sets each env's phase-0 gripper state. A flip counts once the new state has held
        for ``hold_steps`` commands, so a one-action blip does not skip a phase. The count is not capped:
        whoever reads it clamps it to the latents it has (the last phase's latent stays).
        """
        phase = self.phases(closed.shape[0], closed.device)
        if self._closed is None:
            self._closed, self._hold = closed, torch.zeros_like(phase)
            return torch.zeros_like(closed, dtype=torch.bool)
        self._hold = torch.where(closed != self._closed, self._hold + 1, 0)
        switch = self._hold >= hold_steps
        if bool(switch.any()):
            self.phase = phase + switch.long()
            self._closed = torch.where(switch, closed, self._closed)
            self._hold = torch.where(switch, 0, self._hold)
        return switch
