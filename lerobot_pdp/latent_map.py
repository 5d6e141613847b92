"""The latent map of a PDP checkpoint: what behaviors its data holds, before a user steers it.

Left, every training behavior's latent (the first two coordinates, or a PCA projection for d_z > 2),
coloured by its mode label, or by its discovered cluster when the data has no labels; right, small
multiples of the behaviors' traces X(tau), one panel per mode, in the same colours. Any checkpoint
works: the traces and labels are stored in it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .atomic import write_figure_atomic  # noqa: E402
from .console import counted  # noqa: E402
from .modes import MIN_CLUSTER_SIZE  # noqa: E402

logger = logging.getLogger(__name__)

MAX_PANELS = 24  # trace panels drawn; more modes are listed in the title
UNLABELLED = -1  # group of the behaviors without a mode label (behavior.UNLABELED), drawn in grey
UNLABELLED_COLOR = (0.6, 0.6, 0.6, 1.0)


@dataclass
class MapProjection:
    """The map's plane: the first two latent coordinates (one, padded with 0, for d_z = 1), or the training
    latents' PCA plane for d_z > 2; a point clicked on the map goes back to a latent through it."""

    dim: int
    pca: Any = None  # sklearn PCA fitted on the training latents, when dim > 2

    @classmethod
    def fit(cls, z: np.ndarray) -> MapProjection:
        if z.shape[1] <= 2:
            return cls(z.shape[1])
        from sklearn.decomposition import PCA

        return cls(z.shape[1], PCA(2, random_state=0).fit(z))

    @property
    def axis_labels(self) -> tuple[str, str]:
        return ("PC 1", "PC 2") if self.pca is not None else ("z[0]", "z[1]") if self.dim == 2 else ("z[0]", "")

    def to_map(self, z: np.ndarray) -> np.ndarray:
        """Map coordinates [N, 2] of latents [N, d_z]."""
        z = np.asarray(z, dtype=float).reshape(-1, self.dim)
        if self.pca is not None:
            return self.pca.transform(z)
        return z if self.dim == 2 else np.c_[z, np.zeros(len(z))]

    def to_latent(self, xy: np.ndarray) -> np.ndarray:
        """Latents [N, d_z] of map points [N, 2] (for d_z > 2: the point of the PCA plane)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.pca is not None:
            return self.pca.inverse_transform(xy)
        return xy[:, : self.dim]


@dataclass
class LatentMap:
    """A drawn latent map: the figure, its scatter's axes, the projection, and each behavior's group."""

    figure: Any
    axes: Any
    projection: MapProjection
    groups: np.ndarray  # per behavior: its mode label or discovered cluster
    colors: dict[int, Any]


def draw_latent_map(policy, out_png: str | Path, k: int | None = None, title: str | None = None) -> Path:
    """Draw ``policy``'s latent map into ``out_png``; ``k`` fixes the number of discovered clusters."""
    fig = latent_map_figure(policy, k, title).figure
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    write_figure_atomic(fig, out_png, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out_png


def groups_k(policy, k: int | None) -> int | None:
    """How many groups the unlabelled training episodes are drawn in (the explorer's modes too): ``k``; None when
    there are labels or enough episodes to find the modes in; with fewer (a small robot dataset), one group per
    episode, said once: a map that refused them would show nothing."""
    bank = policy.model.bank
    if k is not None or bank.labelled() or len(bank.mode) == 0:
        return k
    n = len(bank.episode[~bank.is_taught()].unique())  # the bank's episodes: no encoding needed
    if n >= 2 * MIN_CLUSTER_SIZE:
        return None
    logger.warning("%s without mode labels: too few to find modes in (%d or more; --k K groups them); each episode "
                   "is a group of its own", counted(n, "training episode"), 2 * MIN_CLUSTER_SIZE)
    return n


def latent_map_figure(policy, k: int | None = None, title: str | None = None) -> LatentMap:
    """``policy``'s latent map as a figure (the caller closes it); ``k`` fixes the number of discovered clusters."""
    table = policy.behavior_table()
    z, episode, mode = table["z"], table["episode"], table["mode"]
    if len(z) == 0:
        raise ValueError("the policy has no training behaviors (a checkpoint trained with lerobot-train has them)")
    k = groups_k(policy, k)
    bank = policy.model.bank
    taught = bank.is_taught().cpu().numpy()
    mode_names = policy.config.mode_names or {}
    if bank.labelled() and k is None:
        groups, what = mode, "mode label"
        names = {int(m): mode_names.get(str(int(m)), "") for m in np.unique(mode[mode >= 0])}
        for m in set(bank.taught_modes()) & set(names):  # learned from one demonstration, not the data
            names[m] = f"{names[m]}, taught" if names[m] else "taught"
    else:  # the training episodes' clusters, then each taught mode (no cluster's) as a group of its own
        found = policy.discover_modes(k=k)
        group_of = {m: found.k + i for i, m in enumerate(bank.taught_modes())}  # its id, unless a k given reaches it
        groups = np.array([group_of[int(m)] if t else found.labels[int(e)]
                           for e, m, t in zip(episode, mode, taught, strict=True)])
        what = f"discovered cluster (k = {found.k})"
        names = {c: counted(int((groups[~taught] == c).sum()), "behavior") for c in range(found.k)}
        names.update({g: f"mode {m}, taught: {mode_names.get(str(m), '')}" for m, g in group_of.items()})
    projection = MapProjection.fit(z)
    xy, axes_label = projection.to_map(z), projection.axis_labels
    ids = sorted(int(g) for g in np.unique(groups) if g >= 0)
    if len(ids) <= 20:
        cmap = plt.get_cmap("tab20" if len(ids) > 10 else "tab10")
        color = {g: cmap(i) for i, g in enumerate(ids)}
    else:  # more groups than a qualitative map has colours: evenly spaced hues, none repeated
        cmap = plt.get_cmap("turbo")
        color = {g: cmap(i / (len(ids) - 1)) for i, g in enumerate(ids)}
    unlabelled = int((groups < 0).sum())  # behaviors of episodes without a mode label, when others have one
    if unlabelled:
        color[UNLABELLED] = UNLABELLED_COLOR
        names[UNLABELLED] = "unlabelled"
    drawn = ids + [UNLABELLED] * bool(unlabelled)
    taught_groups = {int(g) for g in np.unique(groups[taught])}
    # past MAX_PANELS the taught modes' panels come first: they are what a taught checkpoint's map is looked at for
    shown = sorted([g for g in drawn if g in taught_groups]
                   + [g for g in drawn if g not in taught_groups][:max(0, MAX_PANELS - len(taught_groups))],
                   key=drawn.index) if len(drawn) > MAX_PANELS else drawn
    cols = min(4, max(1, len(shown)))
    rows = -(-len(shown) // cols)
    fig = plt.figure(figsize=(6 + 2.4 * cols, max(5.0, 2.2 * rows)))
    grid = fig.add_gridspec(max(rows, 1), cols + 2)
    ax = fig.add_subplot(grid[:, :2])
    phase = policy.behavior_phase().cpu().numpy()
    for g in drawn:
        tag = "" if g == UNLABELLED else f"{g}" + (f" ({names[g]})" if g in taught_groups and len(drawn) > 12 else "")
        label = ": ".join(x for x in (tag, names[g] if names[g] and len(drawn) <= 12 else "") if x)
        for ph in np.unique(phase):
            sel = (groups == g) & (phase == ph)
            ax.scatter(xy[sel, 0], xy[sel, 1], s=14, color=color[g], marker="os^v"[int(ph) % 4],
                       label=label if ph == 0 else None)
            if tag and sel.any():
                # beside (up and right, in points) the point of each of the group's phases nearest their mean: the
                # phases of one mode sit in different places, and a spread cluster's mean lies between its points
                pts = xy[sel]
                at = pts[np.linalg.norm(pts - pts.mean(0), axis=1).argmin()]
                ax.annotate(tag, at, xytext=(5, 5), textcoords="offset points", fontsize=8,
                            ha="left", va="bottom", weight="bold")
    active = policy.steering.latent.detach().cpu().numpy()  # an adapted checkpoint's (or set_latent's) latent
    if len(active):
        where = projection.to_map(active)
        source = (policy.steering.provenance or {}).get("source", "set_latent")
        ax.scatter(where[:, 0], where[:, 1], marker="D", s=70, color="white", edgecolor="k", lw=1.5, zorder=6,
                   label=f"active latent ({source})")
    ax.set_xlabel(axes_label[0])
    ax.set_ylabel(axes_label[1])
    ax.set_title(f"latent map: {counted(len(z), 'behavior')}" + (f" ({unlabelled} unlabelled, grey)" if unlabelled else "") +
                 f", coloured by {what}" +
                 (" (markers = phases)" if len(np.unique(phase)) > 1 else ""), fontsize=10)
    if len(drawn) <= 12:
        ax.legend(fontsize=7, loc="best")
    traces = policy.model.bank.traces.cpu().numpy()
    # the two trace dims the behaviors differ most along (3-D routes may differ in height alone): the spread
    # across behaviors at each point of the (resampled) traces, averaged along them
    spread = traces.var(0).mean(0)
    d0, j = sorted(np.argsort(spread)[::-1][:2].tolist()) if traces.shape[2] > 1 else (0, 0)
    first = None
    for i, g in enumerate(shown):  # one scale for all panels: the routes compare at a glance
        tax = fig.add_subplot(grid[i // cols, 2 + i % cols], sharex=first, sharey=first)
        first = first or tax
        for t in traces[groups == g]:
            tax.plot(t[:, d0], t[:, j], color=color[g], lw=0.8, alpha=0.7)
        tax.set_title(names[g] if g == UNLABELLED else f"{g}" + (f": {names[g]}" if names[g] else ""), fontsize=8)
        tax.tick_params(labelsize=6)
    more = (f"; traces of {len(shown)} of {len(drawn)} shown" + (", taught modes first" if taught_groups else "")
            if len(drawn) > MAX_PANELS else "")
    taught = " and taught modes" if len(policy.model.bank.taught) else ""
    fig.suptitle(title or f"behaviors of the training data{taught} (traces: trace dims {d0} and {j}, the two they "
                 f"spread most along{more})", fontsize=11)
    fig.tight_layout()
    return LatentMap(fig, ax, projection, groups, color)
