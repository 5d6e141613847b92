"""Behavior traces X(tau) and the trajectory VAE that maps them to the behavior latent z.

Data flow (paper Sec. 3.1): whole demonstrations -> behavior traces (selected state dims, optionally
split into gripper phases, resampled to a fixed length) -> soft-DTW distance matrix delta^X (computed
once per dataset) -> trajectory VAE trained with L_rec + beta_KL * L_KL + beta_geo * L_geo, where
L_geo = mean over pairs (|mu_i - mu_j| - kappa * delta^X_ij)^2.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from .atomic import write_file_atomic
from .distributed import main_process_first
from .episodes import check_finite, episode_first_tasks, parse_task_mode, parse_task_name, read_episodes
from .lerobot_command import command_line_value, lerobot_train_episodes, running_lerobot_train, train_value

logger = logging.getLogger(__name__)

UNLABELED = -1  # mode id of a behavior whose task string carries no "mode <id>: ..." label


# ----------------------------------------------------------------------------- traces


def resample(x: np.ndarray, length: int) -> np.ndarray:
    """Linear-in-time resampling of a [T, d] sequence to [length, d] (T == 1 repeats the point)."""
    x = np.asarray(x, dtype=np.float64)
    if x.shape[0] == 1:
        return np.repeat(x, length, axis=0)
    src = np.linspace(0.0, 1.0, x.shape[0])
    dst = np.linspace(0.0, 1.0, length)
    return np.stack([np.interp(dst, src, x[:, j]) for j in range(x.shape[1])], axis=1)


def normalize_trace(x: np.ndarray, mode: str) -> np.ndarray:
    """``none`` | ``start`` (subtract the start point) | ``endpoints`` (also divide by |end - start|)."""
    if mode == "none":
        return x
    x = x - x[:1]
    if mode == "endpoints":
        span = float(np.linalg.norm(x[-1]))
        x = x / max(span, 1e-6)
    return x


def gripper_segments(actions: np.ndarray, dim: int, threshold: float, min_length: int = 2) -> list[tuple[int, int]]:
    """Split frames [0, T) into phases at changes of ``actions[:, dim] > threshold`` (open/close events).

    Runs shorter than ``min_length`` frames take the state of a neighbouring run: inside the episode
    (gripper chatter) the run before them, so a one-frame blip neither starts a phase nor cuts one in two;
    at either end the run next to them, because a phase that short carries no behavior. (An expert that
    stops the episode one frame after opening the gripper otherwise adds a one-frame "release" phase whose
    trace is a constant -- a third of all behaviors and of every fitting batch spent on nothing.)
    """
    closed = (np.asarray(actions)[:, dim] > threshold).copy()
    t = 1
    while t < len(closed):
        if closed[t] != closed[t - 1]:
            run_end = t
            while run_end < len(closed) and closed[run_end] == closed[t]:
                run_end += 1
            if run_end - t < min_length:
                closed[t:run_end] = closed[t - 1]  # chatter, or a too-short last run: joins the run before
            t = run_end
        else:
            t += 1
    changes = np.flatnonzero(closed[1:] != closed[:-1]) + 1
    if len(changes) and changes[0] < min_length:
        closed[: changes[0]] = closed[changes[0]]  # a too-short first run joins the run after it
    cuts = [0] + [t for t in range(1, len(closed)) if closed[t] != closed[t - 1]] + [len(closed)]
    return list(zip(cuts[:-1], cuts[1:], strict=True))


def make_trace(states: np.ndarray, dims: list[int] | None, length: int, normalize: str) -> np.ndarray:
    """X(tau): the selected dims of ``states`` [T, D], normalised and resampled to [length, d]."""
    x = np.asarray(states, dtype=np.float64)
    if dims is not None:
        x = x[:, dims]
    return resample(normalize_trace(x, normalize), length)


@dataclass
class BehaviorTraces:
    """All behaviors of a dataset: one per episode, or one per gripper phase of each episode."""

    traces: np.ndarray  # [N, L, d] float64
    episode_index: np.ndarray  # [N] dataset episode index
    start: np.ndarray  # [N] first frame (inclusive) of the behavior in its episode
    global_start: np.ndarray  # [N] the same frame as a dataset-wide `index` (what training batches carry)
    end: np.ndarray  # [N] last frame (exclusive)
    mode: np.ndarray  # [N] mode id from the task string, UNLABELED if none
    mode_names: dict[int, str]
    # episodes lerobot-train holds out for its eval loss (--dataset.eval_split): encoded, never trained on
    held_out: frozenset[int] = frozenset()

    def __len__(self) -> int:
        return len(self.traces)


def build_behavior_traces(episodes: dict[int, dict], trace_key: str, trace_dims: list[int] | None, length: int,
                          normalize: str, gripper_dim: int | None = None, gripper_threshold: float = 0.0,
                          min_length: int = 1, source: str = "") -> BehaviorTraces:
    """Turn whole episodes into behaviors (split on gripper events when ``gripper_dim`` is set); ``source``: where
    they were read (a dataset folder), named in errors."""
    traces, ep_idx, starts, gstarts, ends, modes = [], [], [], [], [], []
    named: dict[int, dict[str, list[int]]] = {}  # mode id -> name -> its episodes (two names: two modes merged?)
    for ep, item in episodes.items():
        states = item[trace_key]
        check_finite(trace_key, states, f"episode {ep}")
        if len(states) < min_length:
            short = sorted(e for e, it in episodes.items() if len(it[trace_key]) < min_length)
            raise ValueError(f"episode {ep} has {len(states)} frames{f' ({source})' if source else ''}; PDP needs at "
                             f"least {min_length} (its observation history, n_obs_steps). Episodes this short: "
                             f"{short[:10]}{' ...' if len(short) > 10 else ''}: leave them out (--dataset.episodes "
                             f"lists the episodes to train on) or train with --policy.n_obs_steps={max(1, len(states))}")
        if "mode" in item:  # an episode-level label (meta/mode_labels.json) leaves the task string alone
            mode, name = int(item["mode"]), item.get("mode_name")
        elif isinstance(mode := parse_task_mode(item.get("task", "")), int):  # "mode <id>: <name>"
            name = parse_task_name(item["task"])
        else:  # e.g. a language instruction: no label (modes can be discovered, see PDPPolicy.discover_modes)
            mode = UNLABELED
        if mode != UNLABELED:
            named.setdefault(mode, {}).setdefault(name or "", []).append(ep)
        segs = [(0, len(states))]
        if gripper_dim is not None:
            segs = gripper_segments(item["action"], gripper_dim, gripper_threshold)
        for a, b in segs:
            traces.append(make_trace(states[a:b], trace_dims, length, normalize))
            ep_idx.append(ep)
            starts.append(a)
            gstarts.append(item.get("from_index", 0) + a)
            ends.append(b)
            modes.append(mode)
    names = {mode: next((n for n in by_name if n), str(mode)) for mode, by_name in named.items()}  # the first given
    for mode, by_name in named.items():
        given = {n: eps for n, eps in by_name.items() if n}
        if len(given) > 1:  # e.g. two recordings merged, each labelled from mode 0
            logger.warning("mode %d has %d names: %s; PDP trains them as one mode named %r (one mean latent). If they "
                           "are different behaviours, give them different mode ids (lerobot-pdp label-modes)", mode,
                           len(given), "; ".join(f"{n!r} (episodes {eps[:8]}{', ...' if len(eps) > 8 else ''})"
                                                 for n, eps in given.items()), names[mode])
    if gripper_dim is not None and len(traces) == len(episodes):  # asked for phases, and not one gripper event
        g = np.concatenate([np.asarray(item["action"])[:, gripper_dim] for item in episodes.values()])
        raise ValueError(f"segment_gripper_dim={gripper_dim}: no episode's gripper command (action[{gripper_dim}], "
                         f"values in [{g.min():.4g}, {g.max():.4g}]) crosses segment_gripper_threshold="
                         f"{gripper_threshold:g}, so no episode splits into phases. Set --policy."
                         "segment_gripper_threshold between the gripper's open and closed values (raw, as recorded), "
                         "or leave segment_gripper_dim unset for one latent per episode")
    return BehaviorTraces(np.stack(traces), np.array(ep_idx), np.array(starts), np.array(gstarts), np.array(ends),
                          np.array(modes), names)


def trace_distances(traces: np.ndarray, gamma: float, normalize: bool, cache_dir: str | Path | None = None,
                    progress: bool = True, report: dict[str, str] | None = None) -> np.ndarray:
    """delta^X: all-pairs soft-DTW between traces, cached on disk by content hash (traces are fixed data).

    Under multi-process training rank 0 goes first and caches the matrix, which the other ranks then read
    instead of computing it again (see ``distributed.py``). ``report["source"]`` says which happened here:
    ``"computed"`` or ``"read from cache"``.
    """
    with main_process_first():
        d = _trace_distances(traces, gamma, normalize, cache_dir, progress, report if report is not None else {})
    off = ~np.eye(len(d), dtype=bool)
    zero = int((d[off] <= 0).sum())  # soft-DTW values <= 0 are clamped to 0
    if zero > off.sum() // 10 and not normalize:  # identical traces aside, a gamma large for these traces
        _, ids = np.unique(np.asarray(traces).reshape(len(traces), -1), axis=0, return_inverse=True)
        zero = int(((d <= 0) & (ids.reshape(-1)[:, None] != ids.reshape(-1)[None, :])).sum())  # different traces only
    if zero > off.sum() // 10 and not normalize:
        logger.warning("soft-DTW with sdtw_gamma=%g puts %d of the %d distances between different behaviours at 0 "
                       "(soft-DTW dipped below 0 and was clamped): the geometry term treats those pairs as one "
                       "behaviour. Use a smaller --policy.sdtw_gamma (default 1e-5), or --policy.sdtw_normalize=true "
                       "(the soft-DTW divergence, >= 0 by construction)", gamma, zero, int(off.sum()))
    return d


def _trace_distances(traces: np.ndarray, gamma: float, normalize: bool, cache_dir: str | Path | None,
                     progress: bool, report: dict[str, str]) -> np.ndarray:
    from .soft_dtw import soft_dtw_cdist

    traces = np.ascontiguousarray(traces, dtype=np.float64)
    key = hashlib.sha1(traces.tobytes() + f"{traces.shape}|{gamma}|{normalize}".encode()).hexdigest()[:16]
    cache = None
    if cache_dir is None:
        cache_dir = os.environ.get("LEROBOT_PDP_CACHE", Path.home() / ".cache" / "lerobot_pdp")
    try:
        cache = Path(cache_dir) / f"trace_distances_{key}.npy"
        if cache.is_file():
            d = np.load(cache)
            if d.shape == (len(traces), len(traces)) and np.isfinite(d).all():
                report["source"] = "read from cache"
                return d
            logger.warning("soft-DTW cache %s holds a %s matrix%s, not the %d x %d of these traces: recomputing it",
                           cache, d.shape, "" if np.isfinite(d).all() else " with non-finite values", len(traces),
                           len(traces))
    except (ValueError, EOFError) as e:  # a damaged file (cut off while written by an older version, ...)
        logger.warning("soft-DTW cache %s is unreadable (%s): recomputing it", cache, e)
    except OSError:
        cache = None
    d = np.asarray(soft_dtw_cdist(traces, gamma, normalize=normalize, progress=progress), dtype=np.float64)
    d = np.maximum(d, 0.0)  # soft-DTW can dip a hair below 0 (-gamma*log #paths); distances are >= 0
    np.fill_diagonal(d, 0.0)
    report["source"] = "computed"
    if cache is not None:
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            write_file_atomic(cache, lambda tmp: np.save(tmp, d))
        except OSError as e:  # a read-only home must not stop training
            logger.warning("could not cache trace distances at %s: %s", cache, e)
    return d


def prior_mean_distance(latent_dim: int) -> float:
    """E|z - z'| for z, z' ~ N(0, I_d): |z - z'| / sqrt(2) is chi-distributed with d degrees of freedom."""
    return 2.0 * math.exp(math.lgamma((latent_dim + 1) / 2) - math.lgamma(latent_dim / 2))


def choose_kappa(distances: np.ndarray, latent_dim: int) -> float:
    """kappa that puts the mean off-diagonal trace distance at the prior's mean pair distance.

    Why: L_geo fixes latent distances to kappa * delta^X while L_KL pulls codes toward N(0, I). With this
    kappa both terms ask for the same overall scale, so neither is fought by the other and z stays in
    the region that fitting (with its |z|^2 prior term) and interpolation explore.
    """
    n = len(distances)
    if n < 2:
        return 1.0
    off = distances[~np.eye(n, dtype=bool)]
    mean = float(off.mean())
    if not mean > 0:
        return 1.0
    return prior_mean_distance(latent_dim) / mean


# ----------------------------------------------------------------------------- trajectory VAE


def _mlp(dims: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2:
            layers.append(nn.Mish())
    return nn.Sequential(*layers)


class TrajectoryVAE(nn.Module):
    """E_phi: trace [L, d] -> N(mu, diag sigma^2) over z; D_psi: z -> trace (symmetric MLPs).

    Traces are standardised per dim with statistics of the training traces (buffers, saved with the
    policy), so the same encoder applies to new demonstrations at test time.
    """

    def __init__(self, trace_length: int, trace_dim: int, latent_dim: int, hidden_dims: tuple[int, ...]):
        super().__init__()
        self.trace_length, self.trace_dim, self.latent_dim = trace_length, trace_dim, latent_dim
        flat = trace_length * trace_dim
        self.encoder = _mlp([flat, *hidden_dims, 2 * latent_dim])
        self.decoder = _mlp([latent_dim, *reversed(hidden_dims), flat])
        self.register_buffer("trace_mean", torch.zeros(trace_dim))
        self.register_buffer("trace_std", torch.ones(trace_dim))

    def set_trace_stats(self, traces: Tensor) -> None:
        self.trace_mean.copy_(traces.reshape(-1, self.trace_dim).mean(0))
        self.trace_std.copy_(traces.reshape(-1, self.trace_dim).std(0).clamp_min(1e-3))

    def standardize(self, traces: Tensor) -> Tensor:
        return (traces - self.trace_mean) / self.trace_std

    def encode(self, traces: Tensor) -> tuple[Tensor, Tensor]:
        """traces [B, L, d] (raw units) -> (mu, logvar), each [B, d_z]."""
        h = self.encoder(self.standardize(traces).flatten(1))
        mu, logvar = h.chunk(2, dim=-1)
        return mu, logvar.clamp(-12.0, 6.0)

    def decode(self, z: Tensor) -> Tensor:
        """z [B, d_z] -> standardised trace [B, L, d]."""
        return self.decoder(z).view(-1, self.trace_length, self.trace_dim)

    def loss(self, traces: Tensor, distances: Tensor, kappa: float | Tensor, beta_kl: float, beta_geo: float,
             rec_reduction: str = "mean") -> tuple[Tensor, dict[str, Tensor]]:
        """L_embed on a batch of behaviors; ``distances`` [B, B] are their delta^X. ``rec_reduction``: L_rec
        is each trace's squared error averaged ("mean") or summed ("sum", the paper's) over its elements.

        Returns the loss and its terms as detached 0-d tensors (no host sync: the caller reads them once).
        """
        mu, logvar = self.encode(traces)
        z = mu + torch.randn_like(mu) * (0.5 * logvar).exp()
        err = (self.decode(z) - self.standardize(traces)).pow(2)
        rec = err.flatten(1).sum(1).mean() if rec_reduction == "sum" else err.mean()
        kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(-1)).mean()
        geo = mu.new_zeros(())
        if len(mu) > 1 and beta_geo > 0:
            iu = torch.triu_indices(len(mu), len(mu), offset=1, device=mu.device)
            diff = mu[iu[0]] - mu[iu[1]]
            dz = (diff.pow(2).sum(-1) + 1e-12).sqrt()  # eps: the norm's gradient is undefined at 0
            geo = (dz - kappa * distances[iu[0], iu[1]]).pow(2).mean()
        total = rec + beta_kl * kl + beta_geo * geo
        return total, {"embed_rec": rec.detach(), "embed_kl": kl.detach(), "embed_geo": geo.detach()}


def training_behavior_keys(config, features: dict) -> list[str]:
    """The columns :func:`read_training_behaviors` reads from a dataset with ``features``."""
    return [k for k in ("observation.state", "observation.environment_state", "action", config.trace_key)
            if k in features and k not in config.image_features]


def read_training_behaviors(config, root: str | Path, features: dict,
                            episodes: dict[int, dict] | None = None) -> BehaviorTraces:
    """Every whole episode of the local training dataset at ``root`` as behavior traces (LeRobot's loader
    yields windows; the encoder needs whole demonstrations). ``config``: the policy's ``PDPConfig``;
    ``episodes``: the dataset's episodes already read (``read_episodes``, with at least
    :func:`training_behavior_keys`), so a caller that needs them too reads the files once."""
    cfg = config
    keys = training_behavior_keys(cfg, features)
    if episodes is None:
        episodes = read_training_episodes(cfg, root, keys)
    for ep, item in episodes.items():
        for k in keys:
            check_finite(k, item[k], f"dataset {root}, episode {ep}")
    behaviors = build_behavior_traces(
        episodes, cfg.trace_key, cfg.trace_dims, cfg.trace_length, cfg.trace_normalize,
        cfg.segment_gripper_dim, cfg.segment_gripper_threshold, min_length=cfg.n_obs_steps, source=f"dataset {root}",
    )
    split = train_value(sys.argv, "--dataset.eval_split", ("dataset", "eval_split")) if running_lerobot_train(
        sys.argv) else None
    if split:
        behaviors.held_out = frozenset(eval_split_episodes(episodes, float(split), cfg.dataset_episodes,
                                                           episode_first_tasks(root)))
        logger.info("PDP: --dataset.eval_split=%s holds out episodes %s for LeRobot's eval loss: the behavior bank "
                    "encodes them (that loss needs their latents) but the latent space is trained on the other %d",
                    split, sorted(behaviors.held_out), len(episodes) - len(behaviors.held_out))
    return behaviors


def eval_split_episodes(episodes: dict[int, dict], split: float, order: list[int] | None = None,
                        tasks: dict[int, str] | None = None) -> list[int]:
    """The episodes ``lerobot-train --dataset.eval_split=split`` holds out, by LeRobot 0.6's rule
    (``make_train_eval_datasets``): per task, the last ``ceil(n * split)`` of its episodes, in the order of
    ``--dataset.episodes`` (``order``; default the dataset's). An episode's task is its first in the episode
    metadata (``tasks``: :func:`~lerobot_pdp.episodes.episode_first_tasks`, as LeRobot groups it; an episode of
    several tasks may list another first than its first frame's), else its first frame's."""
    per_task: dict[str, list[int]] = {}
    for ep in order if order is not None else sorted(episodes):
        task = (tasks or {}).get(ep)
        per_task.setdefault(str(episodes[ep].get("task", "")) if task is None else task, []).append(ep)
    return [ep for eps in per_task.values() for ep in eps[len(eps) - math.ceil(len(eps) * split):]]


def read_training_episodes(config, root: str | Path, keys: list[str]) -> dict[int, dict]:
    """The episodes the policy trains on, read with ``keys``: under lerobot-train those LeRobot trains on (its
    ``--dataset.episodes``, of the command line or the ``--config_path`` file; else every episode), recorded in
    ``config.dataset_episodes`` (a stale value, e.g. of a checkpoint fine-tuned on other data, is replaced with a
    warning); elsewhere ``config.dataset_episodes`` (None: all). A listed episode the dataset lacks is refused."""
    if running_lerobot_train(sys.argv):
        trains_on = lerobot_train_episodes(sys.argv)
        if config.dataset_episodes is not None and config.dataset_episodes != trains_on:
            chosen = command_line_value(sys.argv, "dataset.episodes") is not None  # said here: no surprise
            logger.log(logging.INFO if chosen else logging.WARNING,
                       "PDP: the behavior bank reads the episodes lerobot-train trains on (%s), not dataset_episodes "
                       "%s (a checkpoint's, a config file's or --policy.dataset_episodes)%s",
                       "every episode" if trains_on is None else trains_on, config.dataset_episodes,
                       "" if chosen else "; choose them with --dataset.episodes")
        config.dataset_episodes = trains_on
        if trains_on is not None:
            logger.info("PDP: the behavior bank reads lerobot-train's --dataset.episodes %s of %s", trains_on, root)
    episodes = read_episodes(root, keys, config.dataset_episodes)
    missing = sorted(set(config.dataset_episodes or ()) - set(episodes))
    if missing:
        raise ValueError(f"{root}: dataset_episodes lists episodes {missing}, which the dataset does not hold")
    return episodes


def check_behaviors(behaviors: BehaviorTraces, root: str | Path, config) -> None:
    """Refuse a behavior trace that is the same in every episode and never moves (a wrong ``trace_key``: every
    soft-DTW distance is 0 and the latent learns nothing); warn when no trace moves within its episode (soft-DTW
    compares paths), and when the dataset holds one episode (:func:`warn_few_episodes`)."""
    where = f"trace_key '{config.trace_key}'" + (f" dims {config.trace_dims}" if config.trace_dims is not None else "")
    if not len(behaviors):
        return
    tol = 1e-9 * max(1.0, float(np.abs(behaviors.traces).max()))  # resampling may move a constant by an ulp
    if np.ptp(behaviors.traces.reshape(-1, behaviors.traces.shape[-1]), axis=0).max() <= tol:
        raise ValueError(f"{root}: the behavior trace ({where}) has the same value in every frame of every episode, "
                         "so every demonstration looks alike and the latent learns nothing; set --policy.trace_key "
                         "(and --policy.trace_dims) to a state-like vector that moves, e.g. end-effector positions")
    if len(behaviors) > 1 and np.ptp(behaviors.traces, axis=0).max() <= tol:
        logger.warning("%s: every behavior trace (%s, trace_length %d) is the same, so soft-DTW finds no distance "
                       "between demonstrations and every latent comes out alike: nothing to steer between. If the "
                       "demonstrations do differ, give traces that show it (a longer --policy.trace_length, other "
                       "--policy.trace_dims)", root, where, behaviors.traces.shape[1])
    elif np.ptp(behaviors.traces, axis=1).max() <= tol:
        logger.warning("%s: the behavior trace (%s) never changes within an episode: soft-DTW compares paths, so "
                       "PDP tells the demonstrations apart by where they are only; a state-like vector that moves "
                       "(end-effector positions) works best", root, where)
    warn_few_episodes(behaviors, root, config.beta_geo)
    length = {int(e): int(behaviors.end[behaviors.episode_index == e].max()) for e in np.unique(behaviors.episode_index)}
    short = [e for e, n in length.items() if n < config.horizon]
    if short:  # trains (the chunk's padding is masked), but fit_latent / teach refuse such a demonstration
        # LeRobot's sampler starts no window in an episode's last drop_n_last_frames frames: none in one that short
        skipped = [e for e in short if length[e] <= config.drop_n_last_frames]
        logger.warning("%s: %d episode(s) are shorter than one action chunk (horizon %d frames): %s. %s a "
                       "demonstration that short cannot be fitted or taught; record longer episodes or train with a "
                       "shorter --policy.horizon", root, len(short), config.horizon,
                       ", ".join(f"{e} ({length[e]} frames)" for e in short[:10]) + (", ..." if len(short) > 10 else ""),
                       f"LeRobot's sampler skips {len(skipped)} of them whole (no more frames than drop_n_last_frames="
                       f"{config.drop_n_last_frames}): the denoiser never trains on them, though their latents join the "
                       "latent space; the others train with each chunk padded past the episode's end; " if skipped else
                       "PDP trains on them (each chunk padded past the episode's end), but")


def warn_few_episodes(behaviors: BehaviorTraces, root: str | Path, beta_geo: float) -> None:
    """Warn once when training reads one episode (the dataset holds one, or ``--dataset.episodes`` selects one):
    the latent then has nothing to be steered between, and with one behavior the geometry term L_geo (over pairs
    of behaviors) is 0."""
    if len(np.unique(behaviors.episode_index)) > 1:
        return
    why = ("its geometry term L_geo compares pairs of behaviors and is 0 with one" if len(behaviors) < 2 and beta_geo > 0
           else "there is one demonstrated behavior")
    logger.warning("PDP trains on one episode of %s: it trains, but its latent learns no behavior geometry "
                   "(%s), so steering has nothing to choose between; record several demonstrations of each "
                   "behavior", root, why)
