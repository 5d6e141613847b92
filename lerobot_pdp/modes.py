"""Modes of the training behaviors when the data has no mode labels: clusters of their latents.

Most LeRobot datasets carry language instructions, not mode labels. PDP's latent space is aligned with
trajectory similarity, so demonstrations that took the same route sit together on the latent map:
clustering the training episodes' latents recovers the modes. scikit-learn does the clustering
(k-means, several restarts) and the choice of k (the silhouette score, highest wins).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

logger = logging.getLogger(__name__)

# Default upper bound of k: half the episodes (a mode of one demonstration is not a mode), at most this
# many candidates (each is a k-means fit: the search's cost).
MAX_K_LIMIT = 100


@dataclass
class DiscoveredModes:
    """Clusters of the training episodes on the latent map."""

    labels: dict[int, int]  # training episode index -> cluster id
    means: dict[int, Tensor]  # cluster id -> mean latent, [d_z] (or [n_phases, d_z] for per-phase latents)
    k: int  # number of clusters
    silhouette: dict[int, float] = field(default_factory=dict)  # candidate k -> silhouette score (k chosen: max)


def episode_features(z: np.ndarray, episode: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One row per training episode: its behaviors' latents in phase order, concatenated. Returns
    (episode indices [E], features [E, n_phases * d_z])."""
    episodes = np.unique(episode)
    counts = {int(e): int((episode == e).sum()) for e in episodes}
    if len(set(counts.values())) != 1:
        raise ValueError(f"episodes have different numbers of phases ({sorted(set(counts.values()))}); mode "
                         "discovery compares whole episodes and needs the same phases in each")
    rows = [z[episode == e][np.argsort(phase[episode == e])].reshape(-1) for e in episodes]
    return episodes, np.stack(rows)


def cluster_episodes(features: np.ndarray, k: int | None = None, max_k: int | None = None, seed: int = 0
                     ) -> tuple[np.ndarray, int, dict[int, float]]:
    """Cluster ids [E] of the episodes' features; ``k=None`` picks k in 2..max_k by silhouette score
    (``max_k=None``: half the episodes, at most ``MAX_K_LIMIT``).

    Cluster ids are numbered by their first episode (the cluster holding episode row 0 is 0, ...), so the
    result does not depend on k-means' internal order.
    """
    from sklearn.cluster import KMeans
    from sklearn.metrics import silhouette_score

    n = len(features)
    if k is not None and not 1 <= k <= n:
        raise ValueError(f"k must be between 1 and the number of training episodes ({n}), got {k}")
    if max_k is not None and max_k < 2:
        raise ValueError(f"max_k must be at least 2 (the smallest k tried), got {max_k}")
    scores: dict[int, float] = {}
    if k is None:
        if n < 3:
            raise ValueError(f"choosing k needs at least 3 training episodes, got {n}; pass k")
        best = None
        if max_k is None:
            max_k = min(max(2, n // 2), MAX_K_LIMIT)
        top = min(max_k, n - 1)
        for cand in range(2, top + 1):
            labels = KMeans(cand, n_init=10, random_state=seed).fit_predict(features)
            if len(np.unique(labels)) < 2:
                continue
            scores[cand] = float(silhouette_score(features, labels))
            if best is None or scores[cand] > scores[best[0]]:
                best = (cand, labels)
        if best is None:
            raise ValueError("the training latents do not split into clusters (all identical?); pass k=1")
        k, labels = best
        if k == top < n - 1:  # the search stopped at its bound, which then decided k: say so
            logger.warning("discover_modes chose k = %d, the largest candidate; there may be more modes "
                           "(pass a larger max_k)", k)
    else:
        labels = KMeans(k, n_init=10, random_state=seed).fit_predict(features) if k > 1 else np.zeros(n, int)
    order = {old: new for new, old in enumerate(dict.fromkeys(labels.tolist()))}
    return np.array([order[x] for x in labels.tolist()]), k, scores


def discover(z: np.ndarray, episode: np.ndarray, phase: np.ndarray, k: int | None = None,
             max_k: int | None = None, seed: int = 0) -> DiscoveredModes:
    """Cluster training episodes by their latents (``z`` [N, d_z] per behavior, with its episode and phase)."""
    episodes, feats = episode_features(z, episode, phase)
    labels, k, scores = cluster_episodes(feats, k, max_k, seed)
    n_phases, d = feats.shape[1] // z.shape[1], z.shape[1]
    means = {}
    for c in range(k):
        m = torch.as_tensor(feats[labels == c].mean(0), dtype=torch.float32).view(n_phases, d)
        means[c] = m[0] if n_phases == 1 else m
    return DiscoveredModes({int(e): int(c) for e, c in zip(episodes, labels, strict=True)}, means, k, scores)
