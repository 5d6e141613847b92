"""Paths between two latents: what ``PDPPolicy.interpolate`` returns (sweeping between modes)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from .steering_state import as_latent_tensor


def interpolate(z_a: Tensor, z_b: Tensor, n: int, path: str = "linear") -> Tensor:
    """``n`` latents from ``z_a`` to ``z_b`` (endpoints included), [n, *z_a.shape].

    ``linear``: straight line; between two clusters on opposite sides of the latent map it passes
    through the map's centre, i.e. through behaviors that lie between opposite routes.
    ``elliptical``: an arc around the origin in the plane of ``z_a`` and ``z_b``, angle and radius
    interpolated linearly (a sweep around the ring of clusters; for orthogonal codes of equal
    norm it is ``z_a cos(t) + z_b sin(t)``, t in [0, pi/2]). It keeps the radius between |z_a| and
    |z_b|, so it visits the clusters between the two ends instead of the centre; opposite codes span
    no plane, and the arc then turns towards the coordinate axis least aligned with ``z_a``. Each row
    of a per-phase latent [P, d_z] gets its own arc.
    """
    z_a, z_b = as_latent_tensor(z_a), as_latent_tensor(z_b)
    if z_a.shape != z_b.shape:
        raise ValueError(f"z_a {tuple(z_a.shape)} and z_b {tuple(z_b.shape)} must have the same shape")
    for name, z in (("z_a", z_a), ("z_b", z_b)):
        if not bool(torch.isfinite(z).all()):
            raise ValueError(f"{name} {z.tolist()} has non-finite values; both ends must be finite latents")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"n must be an integer >= 2 (both endpoints), got {n!r}")
    if path not in ("linear", "elliptical"):
        raise ValueError(f"path must be 'linear' or 'elliptical', got {path!r}")
    t = torch.linspace(0, 1, n, device=z_a.device).view(-1, *([1] * z_a.dim()))  # latents on a GPU too
    line = (1 - t) * z_a + t * z_b
    if path == "linear" or z_a.dim() == 0 or z_a.shape[-1] < 2:
        return line
    eps = 1e-8
    r_a, r_b = z_a.norm(dim=-1, keepdim=True), z_b.norm(dim=-1, keepdim=True)
    u = z_a / r_a.clamp_min(eps)
    w = z_b - (z_b * u).sum(-1, keepdim=True) * u  # z_b's part orthogonal to z_a
    # opposite (or parallel) codes span no plane: turn towards the basis axis least aligned with z_a
    axis = F.one_hot(u.abs().argmin(-1), u.shape[-1]).to(u)
    fallback = axis - (axis * u).sum(-1, keepdim=True) * u
    degenerate = w.norm(dim=-1, keepdim=True) < 1e-6 * r_b.clamp_min(eps)
    w = torch.where(degenerate, fallback, w)
    v = w / w.norm(dim=-1, keepdim=True).clamp_min(eps)
    phi = torch.atan2((z_b * v).sum(-1, keepdim=True).abs(), (z_b * u).sum(-1, keepdim=True))
    arc = ((1 - t) * r_a + t * r_b) * (u * torch.cos(t * phi) + v * torch.sin(t * phi))
    # a zero endpoint has no direction: the arc is the line there
    return torch.where((torch.minimum(r_a, r_b) < eps).expand_as(z_a), line, arc)
