"""Modes of the training behaviors: per-mode mean latents of labelled data, and, when the data has no mode
labels, clusters of the training episodes.

Most LeRobot datasets carry language instructions, not mode labels. Demonstrations that took the same route
have behavior traces a small soft-DTW divergence apart, the similarity PDP's latent space is trained to
reproduce. Two ways to group them, both with scikit-learn:

- ``"traces"`` (default): the episodes' trace divergences themselves. With k unknown, HDBSCAN finds the
  dense groups and how many there are; with k given, average-linkage agglomerative clustering. The latent
  map is a low-dimensional embedding of these divergences and cannot keep all of them: on kitchen-microwave
  two routes 0.08 apart (within a route: < 0.01) sit next to a route spread over the map, so no partition
  of the 2-D latents recovers the five routes, while the divergences separate them exactly
  (docs/results.md, "Mode discovery without labels").
- ``"latents"``: k-means on the episodes' latents, k chosen by the silhouette score (the first version).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .steer_requests import mode_key

logger = logging.getLogger(__name__)

# Default upper bound of k for the latents' search: half the episodes (a mode of one demonstration is not a
# mode), at most this many candidates (each is a k-means fit: the search's cost).
MAX_K_LIMIT = 100
# HDBSCAN's smallest cluster (and its density neighbourhood, min_samples): three demonstrations. Chosen on the
# validation data of the four benchmark envs (3 to 10 demonstrations per mode) and the tests' 4-route data:
# 3 recovers every mode of all five; 2 also does on the benchmark data but splits the tests' jittered routes
# into 7 groups; 5 merges pick-place's 3-demonstration modes. A route with fewer demonstrations joins its
# nearest mode (reported as outliers).
MIN_CLUSTER_SIZE = 3
# Below this silhouette the clusters found are said to be loose: "weak structure" in Kaufman & Rousseeuw's reading
# of silhouettes (0.26-0.50); not a choice that changes any result, only when a warning is given.
LOOSE_SILHOUETTE = 0.5
SPACES = ("traces", "latents")


class ModeLatents(dict):
    """Mode id -> mean latent, as ``PDPPolicy.mode_latents()`` returns it; a missing mode is a KeyError that lists
    the modes there are (a bare ``KeyError: 99`` leaves the user guessing)."""

    def __init__(self, means: dict[int, Tensor], names: dict | None = None, discovered: bool = False):
        super().__init__(means)
        self.names = {int(k): v for k, v in (names or {}).items()}
        self.discovered = discovered

    def __missing__(self, mode: object) -> Tensor:
        # a one-element integer tensor or array (a cluster id read from a tensor), an id as typed ("3") and a
        # mode's name (as `lerobot-pdp steer --mode` takes them) find their mode too
        if isinstance(mode, (Tensor, np.ndarray)) and (mode.numel() if isinstance(mode, Tensor) else mode.size) == 1:
            value = mode.item()
            if isinstance(value, int) and value in self:
                return self[value]
        if isinstance(mode, str):
            if isinstance(mode_key(mode), int) and mode_key(mode) in self:  # "3", as typed
                return self[mode_key(mode)]
            named = [m for m, n in self.names.items() if n == mode and m in self]
            if len(named) == 1:
                return self[named[0]]
        known = ", ".join(f"{m} ({self.names[m]})" if m in self.names else str(m) for m in sorted(self))
        what = "discovered modes (cluster ids)" if self.discovered else "training modes"
        raise KeyError(f"no mode {mode!r}: the {what} are {known}")


@dataclass
class DiscoveredModes:
    """Clusters of the training episodes on the latent map."""

    labels: dict[int, int]  # training episode index -> cluster id
    means: dict[int, Tensor]  # cluster id -> mean latent, [d_z] (or [n_phases, d_z] for per-phase latents)
    k: int  # number of clusters
    # candidate k -> silhouette score ("latents": every candidate, k chosen = max; "traces": the clustering's
    # own k, on the trace divergences)
    silhouette: dict[int, float] = field(default_factory=dict)
    space: str = "latents"  # what was clustered: "traces" (the behaviors' soft-DTW divergences) or "latents"
    # episodes HDBSCAN left in no group (none of >= MIN_CLUSTER_SIZE close enough), each given its nearest cluster
    outliers: list[int] = field(default_factory=list)


def labelled_mode_latents(z: Tensor, mode: Tensor, phase: Tensor, names: dict | None = None) -> ModeLatents:
    """Mean latent of each labelled mode (``mode`` >= 0) of behaviors with latents ``z`` [N, d_z]: [d_z], or one
    mean per phase, [n_phases, d_z], when episodes are segmented (``phase`` > 0 somewhere)."""
    out = {}
    for m in mode[mode >= 0].unique():
        of_mode = mode == m
        if int(phase.max()) == 0:
            out[int(m)] = z[of_mode].mean(0).cpu()
        else:
            out[int(m)] = torch.stack([z[of_mode & (phase == k)].mean(0)
                                       for k in range(int(phase[of_mode].max()) + 1)]).cpu()
    return ModeLatents(out, names)


def episode_layout(episode: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(episode indices [E], behavior index of each episode's phases in order [E, n_phases]); every episode
    must have the same phases, since mode discovery compares whole episodes."""
    episodes = np.unique(episode)
    rows = [np.flatnonzero(episode == e)[np.argsort(phase[episode == e])] for e in episodes]
    if len({len(r) for r in rows}) != 1:
        raise ValueError(f"episodes have different numbers of phases ({sorted({len(r) for r in rows})}); mode "
                         "discovery compares whole episodes and needs the same phases in each")
    return episodes, np.stack(rows)


def episode_features(z: np.ndarray, episode: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One row per training episode: its behaviors' latents in phase order, concatenated. Returns
    (episode indices [E], features [E, n_phases * d_z])."""
    episodes, idx = episode_layout(episode, phase)
    return episodes, z[idx].reshape(len(episodes), -1)


def episode_distances(d: np.ndarray, episode: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance between whole episodes from their behaviors' soft-DTW divergences ``d`` [N, N]: the square
    root of the sum over phases (phase k of one episode against phase k of the other; a divergence is a
    squared distance). Returns (episode indices [E], distances [E, E])."""
    episodes, idx = episode_layout(episode, phase)
    d = np.maximum((d + d.T) / 2, 0.0)  # soft-DTW is symmetric up to rounding
    out = np.sqrt(sum(d[np.ix_(idx[:, k], idx[:, k])] for k in range(idx.shape[1])))
    np.fill_diagonal(out, 0.0)
    return episodes, out


def cluster_distances(dist: np.ndarray, k: int | None = None, min_cluster_size: int = MIN_CLUSTER_SIZE
                      ) -> tuple[np.ndarray, int, list[int]]:
    """Cluster ids [E] of episodes a precomputed distance [E, E] apart, k, and the rows HDBSCAN left as noise
    (each joined to the cluster at the smallest mean distance). ``k=None``: HDBSCAN chooses the clusters;
    else average-linkage agglomerative clustering into k. Ids are numbered by their first episode."""
    from sklearn.cluster import HDBSCAN, AgglomerativeClustering

    n = len(dist)
    if k is not None and not 1 <= k <= n:
        raise ValueError(f"k must be between 1 and the number of training episodes ({n}), got {k}")
    if min_cluster_size < 2:
        raise ValueError(f"min_cluster_size must be at least 2, got {min_cluster_size}")
    noise: list[int] = []
    if k is None:
        if n < 2 * min_cluster_size:
            raise ValueError(f"finding the modes needs at least {2 * min_cluster_size} training episodes (two "
                             f"modes of min_cluster_size = {min_cluster_size}), got {n}; pass k (--k on the command line)")
        labels = HDBSCAN(min_cluster_size=min_cluster_size, metric="precomputed", copy=True).fit_predict(dist)
        found = sorted(set(labels.tolist()) - {-1})
        if not found:  # no dense group at all: one mode
            labels = np.zeros(n, int)
        else:
            noise = np.flatnonzero(labels == -1).tolist()
            members = labels.copy()  # nearest by the clusters HDBSCAN found, not by earlier assignments
            for i in noise:
                labels[i] = min(found, key=lambda c: dist[i, members == c].mean())
        k = len(set(labels.tolist()))
    elif k == 1:
        labels = np.zeros(n, int)
    else:
        labels = AgglomerativeClustering(n_clusters=k, metric="precomputed", linkage="average").fit_predict(dist)
    order = {old: new for new, old in enumerate(dict.fromkeys(labels.tolist()))}
    return np.array([order[x] for x in labels.tolist()]), k, noise


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
            raise ValueError(f"choosing k needs at least 3 training episodes, got {n}; pass k (--k on the command line)")
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
            raise ValueError("the training latents do not split into clusters (all identical?); pass k=1 (--k 1 on the command line)")
        k, labels = best
        if k == top < n - 1:  # the search stopped at its bound, which then decided k: say so
            logger.warning("discover_modes chose k = %d, the largest candidate; there may be more modes "
                           "(pass a larger max_k)", k)
    else:
        labels = KMeans(k, n_init=10, random_state=seed).fit_predict(features) if k > 1 else np.zeros(n, int)
    order = {old: new for new, old in enumerate(dict.fromkeys(labels.tolist()))}
    return np.array([order[x] for x in labels.tolist()]), k, scores


def discover(z: np.ndarray, episode: np.ndarray, phase: np.ndarray, k: int | None = None,
             max_k: int | None = None, seed: int = 0, distances: np.ndarray | None = None) -> DiscoveredModes:
    """Cluster training episodes (``z`` [N, d_z] per behavior, with its episode and phase): by the behaviors'
    soft-DTW ``distances`` [N, N] when given (``max_k`` unused), else by their latents. The means are each
    cluster's mean latent either way."""
    episodes, feats = episode_features(z, episode, phase)
    outliers: list[int] = []
    if distances is None:
        labels, k, scores = cluster_episodes(feats, k, max_k, seed)
    else:
        if max_k is not None:
            raise ValueError("max_k bounds the search over k of the latents' clustering; clustering the traces "
                             "finds k itself (space='latents' to use max_k)")
        _, dist = episode_distances(distances, episode, phase)  # same episode order as the features
        labels, k, noise = cluster_distances(dist, k)
        outliers = [int(episodes[i]) for i in noise]
        scores = {}
        if 1 < k < len(dist):
            from sklearn.metrics import silhouette_score

            scores[k] = float(silhouette_score(dist, labels, metric="precomputed"))
    if scores.get(k, 1.0) < LOOSE_SILHOUETTE:
        logger.warning("discover_modes: the %d clusters found are loose (silhouette %.2f < %.1f: weak structure): "
                       "routes with fewer than %d demonstrations form no cluster of their own and join others, so a "
                       "cluster's mean latent may lie between routes no demonstration took. Label the episodes "
                       "(lerobot-pdp label-modes) or look at the clusters first (lerobot-pdp latent-map)",
                       k, scores[k], LOOSE_SILHOUETTE, MIN_CLUSTER_SIZE)
    n_phases, d = feats.shape[1] // z.shape[1], z.shape[1]
    means = {}
    for c in range(k):
        m = torch.as_tensor(feats[labels == c].mean(0), dtype=torch.float32).view(n_phases, d)
        means[c] = m[0] if n_phases == 1 else m
    return DiscoveredModes({int(e): int(c) for e, c in zip(episodes, labels, strict=True)}, means, k, scores,
                           "latents" if distances is None else "traces", outliers)
