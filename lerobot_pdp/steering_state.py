"""What a policy acts under between two action chunks: the steering state of a rollout.

A PDP's next chunk is conditioned on the *active latent* (one z, or one per phase for policies segmented at
gripper events), may start its sampler from a fitted noise (one per chunk of the demonstration, played in
order), and each env of a vectorised rollout is in its own phase. :class:`Steering` owns all of it, with
four verbs: ``activate`` (a new latent, and its noises), ``reset`` (a new episode), ``latent_for`` /
``next_noise`` (the next chunk) and ``observe`` (an executed gripper command). It never fits anything: a
fit produces what ``activate`` takes. :class:`ChunkNoises` alone is what the benchmark's DP replays.

The state is small and can be kept: :meth:`Steering.state_tensors` / :meth:`Steering.load_state_tensors`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .phases import PhaseTracker

logger = logging.getLogger(__name__)


class ChunkNoises(nn.Module):
    """Sampler start noises [C, horizon, A], one per new action chunk of an episode in order; the last one
    repeats. Empty: the sampler draws its own noise."""

    def __init__(self, noise: Tensor | None = None):
        super().__init__()
        self.register_buffer("noise", torch.zeros(0, 0, 0) if noise is None else noise.detach().float(),
                             persistent=False)
        self.chunk = 0  # chunks generated since the episode began: which noise comes next

    def __len__(self) -> int:
        return len(self.noise)

    def set(self, noise: Tensor | None) -> None:
        self.noise = self.noise[:0] if noise is None else noise.detach().float().to(self.noise.device)
        self.chunk = 0

    def reset(self) -> None:
        self.chunk = 0

    def next(self, batch_size: int, device: torch.device | str, advance: bool = True) -> Tensor | None:
        """The noise of the next chunk, [batch_size, horizon, A] (None when there are none)."""
        x = self.at(self.chunk, batch_size, device)
        if advance:
            self.chunk += 1
        return x

    def at(self, index: int, batch_size: int, device: torch.device | str) -> Tensor | None:
        """Noise ``index`` (the last one past the end), [batch_size, horizon, A]; None when there are none."""
        if len(self.noise) == 0:
            return None
        x = self.noise[min(index, len(self.noise) - 1)]
        return x.to(device).expand(batch_size, *x.shape)


LATENT_TYPES_HELP = "a tensor, a numpy array or a sequence of floats, shape [d_z] or [M, d_z] (one per phase)"


def as_latent_tensor(z: object) -> Tensor:
    """``z`` as a float tensor; anything that is not numbers (a string such as ``"0.4 -1.2"``, a dict) is a
    TypeError naming the accepted types, not numpy's "could not convert string to float"."""
    if isinstance(z, Tensor):
        return z.float()
    if isinstance(z, str):  # numbers typed as text, or a mode's name meant as its latent
        try:
            numbers = [float(x) for x in z.replace(",", " ").split()]
        except ValueError:
            numbers = None
        hint = f"as numbers: {numbers}" if numbers else f"a mode's latent: policy.mode_latents()[{z!r}]"
        raise TypeError(f"latent must be {LATENT_TYPES_HELP}; got str {z!r} ({hint})")
    if isinstance(z, (int, np.integer)) and not isinstance(z, bool):  # a mode's id, meant as its latent
        raise TypeError(f"latent must be {LATENT_TYPES_HELP}; got int {z!r} (a mode's latent: "
                        f"policy.mode_latents()[{z!r}])")
    if isinstance(z, (bytes, dict)):
        raise TypeError(f"latent must be {LATENT_TYPES_HELP}; got {type(z).__name__} {z!r}")
    try:
        return torch.as_tensor(np.asarray(z, dtype=np.float32))
    except (TypeError, ValueError) as e:
        raise TypeError(f"latent must be {LATENT_TYPES_HELP}; got {type(z).__name__} {z!r} ({e})") from e


class Steering(nn.Module):
    """The active latent(s), the chunk noises fitted with them, and each env's phase.

    An ``nn.Module`` so that ``policy.to(device)`` moves it; its buffers are not part of the weights.
    """

    def __init__(self, latent_dim: int, config: Any = None):
        super().__init__()
        self.latent_dim = latent_dim
        self._config = config  # the policy's: without segment_gripper_dim it never changes phase (one latent)
        # [M, d_z]: empty = the policy's default latent; M > 1 = one per phase, advanced on gripper events
        self.register_buffer("latent", torch.zeros(0, latent_dim), persistent=False)
        self.noises = ChunkNoises()
        self.phases = PhaseTracker()  # which phase latent each env of a rollout is in
        self.episode_latent: Tensor | None = None  # the default latent drawn for this episode
        self.provenance: dict | None = None  # where the active latent came from (kept with an adapted checkpoint)
        self.resets = 0  # episodes started (a chunk generated across a reset is stale: realtime_chunking.py)
        # lerobot-rollout's RTC engine (realtime_chunking.py) replans at its own pace and reports the actions the
        # robot executes; then a chunk planned at the episode's step k starts from noise k // n_action_steps, the
        # noise fitted to the demonstration's frames from there (latent_fitting.fit_chunk_noise), not the next one
        self.by_step = False
        self.executed_steps = 0  # actions executed since the episode began, as reported

    @property
    def active(self) -> bool:
        return len(self.latent) > 0

    @property
    def per_phase(self) -> bool:
        return len(self.latent) > 1

    def activate(self, z: Tensor | Sequence[float] | np.ndarray | None, noise: Tensor | None = None,
                 provenance: dict | None = None) -> None:
        """Make ``z`` ([d_z], or [M, d_z] = one per phase) the active latent, with the chunk noises fitted under
        it (``None``: none; noises of an earlier latent never carry over) and where it came from.
        ``z=None``: the default latent."""
        if z is None:
            self.latent = self.latent[:0]
            provenance = None
        else:
            z = given = as_latent_tensor(z)
            if z.dim() == 1:
                z = z[None]
            if z.dim() != 2 or z.shape[1] != self.latent_dim:
                raise ValueError(f"latent must have shape [{self.latent_dim}] or [M, {self.latent_dim}], "
                                 f"got {tuple(given.shape)}")
            if len(z) > 1 and self._config is not None and self._config.segment_gripper_dim is None:
                raise ValueError(f"got {len(z)} latents {tuple(z.shape)}, one per phase, but this policy has no "
                                 f"phases (trained without segment_gripper_dim): only the first would ever act. "
                                 f"Give one latent [{self.latent_dim}] (of a path from interpolate, one of its rows; "
                                 "of fit_latent, no segments)")
            if not torch.isfinite(z).all():
                raise ValueError(f"latent has non-finite values: {z.tolist()}")
            self.latent = z.detach().to(self.latent.device)
        self.noises.set(noise)  # the phases go on: they count the episode's gripper flips (phases.py)
        self.provenance = provenance

    def reset(self) -> None:
        """A new episode: phases and noises start over, the default latent is drawn anew."""
        self.phases.reset()
        self.noises.reset()
        self.executed_steps = 0
        self.episode_latent = None
        self.resets += 1

    def latent_for(self, batch_size: int, device: torch.device | str,
                   default: Callable[[int], Tensor]) -> Tensor:
        """The latent of the next chunk, [batch_size, d_z]: each env's phase latent, or (nothing active)
        ``default(batch_size)`` drawn once per episode."""
        if len(self.latent) == 1:
            return self.latent[0].to(device).expand(batch_size, -1)
        if len(self.latent) > 1:
            phase = self.phases.phases(batch_size, self.latent.device)
            return self.latent[phase.clamp(max=len(self.latent) - 1)].to(device)
        if self.episode_latent is None or self.episode_latent.shape[0] != batch_size:
            self.episode_latent = default(batch_size).to(device)
        return self.episode_latent

    def next_noise(self, batch_size: int, device: torch.device | str) -> Tensor | None:
        """The fitted noise of the next chunk: the next in order, or (``by_step``) the one of the step reached."""
        if self.by_step:
            return self.noises.at(self.executed_steps // self._config.n_action_steps, batch_size, device)
        return self.noises.next(batch_size, device)

    def observe(self, gripper_closed: Tensor, hold_steps: int) -> bool:
        """An executed gripper command per env ([B] bool), counted whatever latent is active (one per phase may
        come mid-episode); True when some env moved to its next phase latent."""
        moved = self.phases.update(gripper_closed.to(self.latent.device), hold_steps)
        return self.per_phase and bool((moved & (self.phases.phase <= len(self.latent) - 1)).any())

    def state_tensors(self) -> dict[str, Tensor]:
        """The active latent and noises (CPU copies), what an adapted checkpoint keeps."""
        return {"latent": self.latent.detach().cpu(), "noise": self.noises.noise.detach().cpu()}

    def load_state_tensors(self, tensors: dict[str, Tensor], provenance: dict | None = None) -> None:
        noise, latent = tensors.get("noise"), tensors["latent"]
        if len(latent) > 1 and self._config is not None and self._config.segment_gripper_dim is None:
            # saved before several latents were refused on a policy without phases: it acted under the first
            logger.warning("adaptation of %d phase latents on a policy without phases: acting under the first, as "
                           "it did when it was saved", len(latent))
            latent = latent[:1]
        self.activate(latent if len(latent) else None, noise if noise is not None and len(noise) else None,
                      provenance)
