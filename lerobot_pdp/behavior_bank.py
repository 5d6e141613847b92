"""The behaviour bank: the training behaviours of a PDP, as one object.

:class:`BehaviorBank` holds every training behaviour (one per episode, or one per gripper phase of each
episode) and what PDP knows about them:

- **the traces** X(tau) [N, L, d] and **where each sits**: its episode, its frame range in that episode, and its
  first frame as a dataset-wide ``index`` (what training batches carry; ``TAUGHT_START`` for a taught behaviour,
  which has no frames in the training dataset);
- **the modes**: each behaviour's mode label (``UNLABELED`` without one); per-mode mean latents, or, without
  labels, the modes discovered by clustering the episodes (:mod:`lerobot_pdp.modes`);
- **delta^X**, the soft-DTW distance matrix of the traces, and **kappa**, the scale L_geo puts between latent and
  trace distances (``behavior.py``);
- **a checksum** (:meth:`BehaviorBank.digest`), which multi-process training compares across ranks
  (:meth:`BehaviorBank.check_ranks_agree`).

It is filled once from the dataset (:meth:`~BehaviorBank.set`, at training), sized by a checkpoint before that
loads into it (:meth:`~BehaviorBank.resize`), and grows by a taught mode (:meth:`~BehaviorBank.append`). Its
buffers are saved under the first release's flat key names (``CHECKPOINT_KEYS``; ``checkpoint.py`` maps them).

The mode names, the one-hot ablation's latent size and the dataset's frame rate and value names are config fields
(config.json keeps them with the checkpoint): :func:`resolve_dataset_config` sets them from the dataset before the model is built, the one place
the config is written from data. The model and its bank only read the config; a taught mode's name is the one
field :meth:`~BehaviorBank.append` adds to it.
"""

from __future__ import annotations

import hashlib
import logging
import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from .behavior import (
    UNLABELED,
    BehaviorTraces,
    TrajectoryVAE,
    check_behaviors,
    choose_kappa,
    read_training_behaviors,
    trace_distances,
)
from .configuration_pdp import PDPConfig
from .console import latent_text
from .distributed import (
    agree_across_ranks,
    release_process_group_at_exit,
    warn_if_cpu_launch_ran_one_process,
    world,
)
from .episodes import check_camera_sizes, dataset_value_names
from .modes import SPACES, DiscoveredModes, ModeLatents, discover, labelled_mode_latents
from .steering_state import as_latent_tensor

logger = logging.getLogger(__name__)

# The bank's buffers and their checkpoint keys (the first release's, when they were buffers of the model), in
# the order the checksum reads them. All but kappa are sized by the dataset (their first dimension is N).
CHECKPOINT_KEYS = {"traces": "behavior_traces", "episode": "behavior_episode", "start": "behavior_start",
                   "global_start": "behavior_global_start", "end": "behavior_end", "mode": "behavior_mode",
                   "distances": "trace_distance_matrix", "kappa": "geo_kappa"}
DATASET_SIZED = ("traces", "episode", "start", "global_start", "end", "mode", "distances")
# The latents taught behaviours were taught at, [n_taught, d_z] (the bank's last rows), and their checkpoint key:
# not in the checksum, so that a bank's digest is the same as before taught modes existed.
TAUGHT_KEY = "taught_latents"
# global_start of a taught behaviour: it has no frames in the training dataset
TAUGHT_START = -1
# A latent farther than this from every training latent, in RMS standard deviations of them, is an outlier.
FAR_LATENT_SPREADS = 3.0


def onehot_modes(behaviors: BehaviorTraces) -> int:
    """The number of modes, the one-hot ablation's latent size; every behaviour must carry a mode label."""
    n_modes = int(behaviors.mode.max()) + 1 if (behaviors.mode >= 0).any() else 0
    if n_modes < 1 or (behaviors.mode == UNLABELED).any():
        raise ValueError("latent_type='onehot' needs a mode label for every episode (meta/mode_labels.json, "
                         "or task strings 'mode <id>: <name>')")
    return n_modes


def bank_summary(behaviors: BehaviorTraces) -> str:
    """What the training run reads from its dataset, in one line: episodes, behaviours, modes (labelled or not)."""
    episodes = len(np.unique(behaviors.episode_index))
    labelled = sorted({int(m) for m in behaviors.mode if m >= 0})
    if not labelled:
        modes = "no mode labels (mode_latents() discovers the modes by clustering; lerobot-pdp latent-map draws them)"
    else:
        names = ", ".join(f"{m} ({behaviors.mode_names[m]})" if behaviors.mode_names.get(m) else str(m)
                          for m in labelled[:12]) + (", ..." if len(labelled) > 12 else "")
        unlabelled = int(len(np.unique(behaviors.episode_index[behaviors.mode < 0])))
        modes = f"{len(labelled)} labelled mode(s): {names}" + (f"; {unlabelled} episode(s) without a label"
                                                               if unlabelled else "")
    return f"{episodes} episode(s), {len(behaviors)} behavior(s); {modes}"


def resolve_dataset_config(config: PDPConfig, behaviors: BehaviorTraces, dataset_meta: Any = None) -> None:
    """Set the config fields the training dataset decides, before the model is built from the config:
    ``mode_names`` (the episodes' mode labels) and, for the one-hot ablation, ``latent_dim`` (the number of
    modes); from ``dataset_meta`` (LeRobot's dataset metadata), the frame rate and the vector values' names that
    demonstrations and robots are checked against (``dataset_fps``, ``dataset_feature_names``). They are config
    fields because config.json is where a checkpoint keeps them, and LeRobot builds the networks of every later
    load (and a resumed training) from ``config.latent_dim``."""
    logger.info("PDP behavior bank: %s", bank_summary(behaviors))
    # this dataset's names only: a checkpoint trained further on data without labels must not name its discovered
    # clusters after the old data's modes (a taught mode's name is added back where it is kept: checkpoint.py)
    config.mode_names = {str(k): v for k, v in sorted(behaviors.mode_names.items())} or None
    if config.latent_type == "onehot":
        n_modes = onehot_modes(behaviors)
        if config.latent_dim != n_modes:
            logger.info("onehot latent: setting latent_dim = %d (number of modes)", n_modes)
            config.latent_dim = n_modes
    if dataset_meta is not None:
        fps = getattr(dataset_meta, "fps", None)
        config.dataset_fps = float(fps) if isinstance(fps, (int, float)) and not isinstance(fps, bool) else None
        vectors = [k for k in (*config.input_features, *config.output_features, config.trace_key)
                   if k not in config.image_features]
        config.dataset_feature_names = dataset_value_names(dataset_meta.features, list(dict.fromkeys(vectors)))


def dataset_behaviors(config: PDPConfig, dataset_meta: Any) -> BehaviorTraces | None:
    """The training behaviours of the local dataset ``dataset_meta`` describes (as ``lerobot-train`` passes it),
    checked, and the config fields they decide set (:func:`resolve_dataset_config`), before the model is built;
    None without a local dataset. Cameras of another size than the policy's are refused before the soft-DTW."""
    root = getattr(dataset_meta, "root", None)
    if root is None:
        return None
    check_camera_sizes(config.image_features, root, dataset_meta.features)
    behaviors = read_training_behaviors(config, root, dataset_meta.features)
    check_behaviors(behaviors, root, config)
    resolve_dataset_config(config, behaviors, dataset_meta)
    return behaviors


class BehaviorBank(nn.Module):
    """The training behaviours: traces, where they sit, modes, delta^X and kappa (see the module docstring).

    An ``nn.Module`` of buffers, so that ``.to(device)`` moves it and the checkpoint keeps it. Latents are
    computed by the encoder it is given (``vae``): the bank holds data, the model the networks.
    """

    def __init__(self, config: PDPConfig):
        super().__init__()
        cfg = self.config = config
        self.register_buffer("traces", torch.zeros(0, cfg.trace_length, cfg.trace_dim))
        self.register_buffer("episode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("global_start", torch.zeros(0, dtype=torch.long))
        self.register_buffer("end", torch.zeros(0, dtype=torch.long))
        self.register_buffer("mode", torch.zeros(0, dtype=torch.long))
        self.register_buffer("distances", torch.zeros(0, 0))
        self.register_buffer("kappa", torch.tensor(1.0 if cfg.geo_kappa is None else cfg.geo_kappa))
        self.register_buffer("taught", torch.zeros(0, cfg.latent_dim))
        # behaviours L_embed samples from (empty: all); lerobot-train's eval split is left out. Not saved: it is
        # the training run's, set again from its dataset when training resumes
        self.register_buffer("embed_pool", torch.zeros(0, dtype=torch.long), persistent=False)
        self._discovered: tuple[tuple, DiscoveredModes] | None = None  # cached discover_modes() result
        # the demonstrations of the taught modes, by mode (a Demonstration each): rehearsed when teaching again,
        # saved beside the weights (taught_demos.py)
        self.taught_demos: dict[int, Any] = {}
        # what each teaching was (teaching.json's records), by mode: saved beside the weights too
        self.teachings: dict[int, dict[str, Any]] = {}
        # loaded to train on (lerobot-train) with its taught behaviours kept: their demonstrations are rehearsed
        # in every batch (taught_rehearsal.py)
        self.taught_in_training = False

    # ------------------------------------------------------------------ filling it

    def set(self, b: BehaviorTraces) -> None:
        """Take the training behaviours and compute their soft-DTW distance matrix delta^X (and kappa); under
        multi-process training every rank checks it holds the same bank. The config must already be resolved
        for this dataset (:func:`resolve_dataset_config`)."""
        cfg = self.config
        self.traces = torch.as_tensor(b.traces, dtype=torch.float32)
        self.episode = torch.as_tensor(b.episode_index, dtype=torch.long)
        self.start = torch.as_tensor(b.start, dtype=torch.long)
        self.global_start = torch.as_tensor(b.global_start, dtype=torch.long)
        self.end = torch.as_tensor(b.end, dtype=torch.long)
        self.mode = torch.as_tensor(b.mode, dtype=torch.long)
        self._discovered = None
        held = torch.as_tensor(sorted(b.held_out), dtype=torch.long)
        self.embed_pool = (torch.nonzero(~torch.isin(self.episode, held)).flatten() if len(held)
                           else torch.zeros(0, dtype=torch.long))
        if cfg.latent_type == "onehot":
            if cfg.latent_dim != onehot_modes(b):
                raise ValueError(f"latent_type='onehot' with latent_dim {cfg.latent_dim} for {onehot_modes(b)} modes: "
                                 "resolve the config for the dataset first (behavior_bank.resolve_dataset_config)")
            self.distances = torch.zeros(len(b), len(b))
            self.check_ranks_agree("not needed (one-hot latents)")
            return
        report: dict[str, str] = {}
        d = trace_distances(b.traces, cfg.sdtw_gamma, cfg.sdtw_normalize, report=report)
        self.distances = torch.as_tensor(d, dtype=torch.float32)
        kappa = cfg.geo_kappa if cfg.geo_kappa is not None else choose_kappa(d, cfg.latent_dim)
        self.kappa = torch.tensor(float(kappa))
        self.check_ranks_agree(report.get("source", "computed"))

    def resize(self, shapes: dict[str, tuple[int, ...]]) -> None:
        """Give the dataset-sized buffers the shapes a checkpoint holds (``shapes`` by checkpoint key), so that
        it loads into them."""
        for name in DATASET_SIZED:
            if CHECKPOINT_KEYS[name] in shapes:
                setattr(self, name, torch.zeros(shapes[CHECKPOINT_KEYS[name]], dtype=getattr(self, name).dtype))
        if TAUGHT_KEY in shapes:
            self.taught = torch.zeros(shapes[TAUGHT_KEY])
        self._discovered = None

    def append(self, traces: np.ndarray, segments: list[tuple[int, int]], name: str, latents: Tensor,
               mode: int | None = None) -> int:
        """A taught demonstration's phases (``traces`` [M, L, d] with their frame ``segments``) join the bank as a
        new episode of a new mode (one past the last of each, or the id ``mode`` a taught mode had), at
        ``TAUGHT_START``, acting under ``latents`` [M, d_z] (kept: :meth:`latents` returns them for these
        behaviours); delta^X gains their soft-DTW distances (kappa stays), and the config's ``mode_names`` the new
        mode's ``name``. Returns the new mode id."""
        cfg = self.config
        self.taught = torch.cat([self.taught, latents.to(self.taught)])
        traces = torch.as_tensor(traces, dtype=torch.float32, device=self.traces.device)
        n = len(traces)
        mode = int(self.mode.max()) + 1 if mode is None else mode
        episode = int(self.episode.max()) + 1

        def longs(values) -> Tensor:
            return torch.as_tensor(values, dtype=torch.long, device=self.episode.device)

        self.traces = torch.cat([self.traces, traces])
        self.episode = torch.cat([self.episode, longs([episode] * n)])
        self.start = torch.cat([self.start, longs([a for a, _ in segments])])
        self.global_start = torch.cat([self.global_start, longs([TAUGHT_START] * n)])
        self.end = torch.cat([self.end, longs([b for _, b in segments])])
        self.mode = torch.cat([self.mode, longs([mode] * n)])
        d = trace_distances(self.traces.cpu().numpy().astype(np.float64), cfg.sdtw_gamma, cfg.sdtw_normalize,
                            progress=False)
        self.distances = torch.as_tensor(d, dtype=torch.float32, device=self.distances.device)
        cfg.mode_names = {**(cfg.mode_names or {}), str(mode): name}
        self._discovered = None
        return mode

    # ------------------------------------------------------------------ checksum, ranks

    def snapshot(self) -> dict[str, Tensor]:
        """A copy of every buffer, for :meth:`restore`."""
        return {name: getattr(self, name).detach().clone() for name in (*CHECKPOINT_KEYS, "taught")}

    def restore(self, saved: dict[str, Tensor]) -> None:
        """Put back the buffers of a :meth:`snapshot` (taught demonstrations and records of modes it lacks are
        dropped)."""
        for name, t in saved.items():
            setattr(self, name, t)
        self._discovered = None
        taught = self.taught_modes()
        self.taught_demos = {m: d for m, d in self.taught_demos.items() if m in taught}
        self.teachings = {m: r for m, r in self.teachings.items() if m in taught}

    def taught_modes(self) -> list[int]:
        """The ids of the modes taught to the policy (their behaviours sit at ``TAUGHT_START``)."""
        return sorted({int(m) for m in self.mode[self.is_taught()].tolist()})

    def unrehearsable_modes(self) -> list[int]:
        """The taught modes whose demonstration the policy does not keep (taught by a release that kept none, or a
        damaged file): nothing can rehearse them."""
        return [m for m in self.taught_modes() if m not in self.taught_demos]

    @staticmethod
    def same_behaviors(a: dict[str, Tensor], b: dict[str, Tensor]) -> bool:
        """Two snapshots hold the same behaviours: where they sit, their modes and their traces (to float
        tolerance: delta^X and kappa follow from the traces, and a recomputed delta^X may differ in its last bits)."""
        where = ("episode", "start", "end", "global_start", "mode")
        return (all(torch.equal(a[n], b[n]) for n in where) and a["traces"].shape == b["traces"].shape
                and bool(torch.allclose(a["traces"], b["traces"], rtol=1e-5, atol=1e-6)))

    def digest(self) -> str:
        """SHA-1 of the bank (traces, where they sit, modes, delta^X, kappa): equal iff the banks are."""
        h = hashlib.sha1()
        for name, key in CHECKPOINT_KEYS.items():
            t = getattr(self, name).detach().cpu().contiguous()
            h.update(f"{key}{tuple(t.shape)}{t.dtype}".encode())
            h.update(t.numpy().tobytes())
        return h.hexdigest()

    def check_ranks_agree(self, distance_source: str) -> None:
        """Under multi-process training, make sure every rank built the same behavior bank, and log (rank 0)
        which rank computed delta^X and which read it from the cache. A no-op in a single process."""
        rank, size = world()
        if size == 1:
            warn_if_cpu_launch_ran_one_process()
            return
        release_process_group_at_exit()  # lerobot-train's ranks exit after the run (a torch deadlock otherwise)
        digest = self.digest()
        sources = agree_across_ranks("the behavior bank", digest, distance_source)
        if rank == 0:
            logger.info("behavior bank: %d behaviors, identical on all %d ranks (sha1 %s); soft-DTW distances: %s",
                        len(self.traces), size, digest[:12], ", ".join(f"rank {r} {s}" for r, s in enumerate(sources)))

    # ------------------------------------------------------------------ lookups

    def ids(self, episode_index: Tensor, global_index: Tensor | None, check: bool = True) -> Tensor:
        """Behavior (episode, or gripper phase of an episode) of each training sample; ``check``: refuse an
        episode that is not among the training behaviors."""
        if len(self.episode) == 0:
            raise RuntimeError(
                "PDP has no behavior traces: build it with dataset_meta (lerobot-train does) or load a checkpoint"
            )
        ep = episode_index.view(-1, 1).to(self.episode.device)
        match = ep == self.episode.view(1, -1)
        known = match.any(1).all()
        if check and known.device.type == "cpu":
            if not bool(known):
                missing = episode_index.view(-1)[~match.any(1).cpu()].unique().tolist()
                raise KeyError(f"episode(s) {missing} are not among the policy's training episodes "
                               f"({self.episode.unique().numel()} episodes, {len(self.episode)} behaviors)")
        elif check:  # checked on the device: reading the flag back would stall the GPU every training step
            torch._assert_async(known, "a training batch holds episodes that are not among the policy's "
                                       "training episodes (run one step on CPU to see which)")
        if global_index is not None:
            # behaviors of one episode partition its frames in order: take the last one that starts <= frame
            f = global_index.view(-1, 1).to(self.start.device)
            later = match & (self.global_start.view(1, -1) <= f)
            match = torch.where(later.any(1, keepdim=True), later, match)
        ids = torch.arange(match.shape[1], device=match.device).view(1, -1).expand_as(match)
        return torch.where(match, ids, torch.full_like(ids, -1)).max(1).values

    def phase(self) -> Tensor:
        """Phase index of each training behavior within its episode (0 when episodes are not segmented)."""
        same = self.episode.view(-1, 1) == self.episode.view(1, -1)
        earlier = self.start.view(1, -1) < self.start.view(-1, 1)
        return (same & earlier).sum(1)

    def latents(self, vae: TrajectoryVAE, ids: Tensor | None = None) -> Tensor:
        """z_bar = mu_phi(X(tau)) of training behaviors (all, or ``ids``) under the encoder ``vae``; one-hot mode
        codes for that ablation."""
        if self.config.latent_type == "onehot":
            modes = self.mode if ids is None else self.mode[ids]
            return F.one_hot(modes, self.config.latent_dim).float()
        traces = self.traces if ids is None else self.traces[ids]
        z = vae.encode(traces)[0]
        if len(self.taught):  # taught behaviours (the last rows) act under the latent they were taught at
            first = len(self.traces) - len(self.taught)
            idx = torch.arange(len(self.traces), device=z.device) if ids is None else ids.to(z.device)
            pinned = self.taught.to(z)[(idx - first).clamp_min(0)]
            z = torch.where((idx >= first).unsqueeze(-1), pinned, z)
        return z

    def place_taught(self, latents: Tensor) -> None:
        """Move the last taught behaviours' latents (one per phase of the last taught mode) to ``latents``."""
        self.taught[len(self.taught) - len(latents):] = latents.to(self.taught)

    def default_latents(self, vae: TrajectoryVAE, batch_size: int) -> Tensor:
        """The latent a policy acts under when none is active, [batch_size, d_z] on the CPU (see
        ``config.inference_latent``): zero, a prior draw, or a random training behaviour's latent."""
        d = self.config.latent_dim
        if self.config.inference_latent == "zero":
            return torch.zeros(batch_size, d)
        if self.config.inference_latent == "prior" or len(self.traces) == 0:
            return torch.randn(batch_size, d)
        with torch.no_grad():
            ids = torch.randint(0, len(self.traces), (batch_size,), device=self.traces.device)
            return self.latents(vae, ids).cpu()

    def table(self, vae: TrajectoryVAE) -> dict[str, np.ndarray]:
        """Latent of every training behavior with its episode, frame range and mode (for maps/plots)."""
        with torch.no_grad():
            z = self.latents(vae).cpu().numpy()
        return {"z": z, "episode": self.episode.cpu().numpy(), "start": self.start.cpu().numpy(),
                "end": self.end.cpu().numpy(), "mode": self.mode.cpu().numpy()}

    def outlier(self, vae: TrajectoryVAE, z: Any) -> tuple[float, float] | None:
        """(distance to the nearest training latent in spreads, spread) when a row of ``z`` ([d_z] or [M, d_z]: a
        tensor, array or list, as ``set_latent`` takes) lies more than ``FAR_LATENT_SPREADS`` spreads (RMS standard
        deviations of the training latents per dim) from every training latent, else None (also without behaviors)."""
        z = as_latent_tensor(z)
        d = self.config.latent_dim
        if z.dim() not in (1, 2) or z.shape[-1] != d:
            raise ValueError(f"latent has shape {list(z.shape)}; expected [{d}] or [M, {d}] (latent_dim {d})")
        z = z.reshape(-1, d)
        if len(self.traces) < 2:
            return None
        with torch.no_grad():
            train = self.latents(vae).float().cpu()
        spread = float(train.var(0).mean().sqrt())
        if not spread > 0:
            return None
        nearest = float(torch.cdist(z.float().cpu(), train).min(1).values.max()) / spread
        if math.isnan(nearest):  # the distance overflows float32 (|z| ~ 1e19 and up): as far as it gets
            nearest = math.inf
        return (nearest, spread) if nearest > FAR_LATENT_SPREADS else None

    def warn_if_far(self, vae: TrajectoryVAE, z: Tensor) -> None:
        """One warning when ``z`` (a latent just made active) is an :meth:`outlier`: the policy never saw it
        condition an action."""
        far = self.outlier(vae, z)
        if far is not None:
            logger.warning("set_latent: latent %s is %.1f spreads of the training latents from the nearest one "
                           "(warning above %g; spread = their RMS standard deviation per dim, %.3g): the policy "
                           "was never trained there and may act erratically", latent_text(z), far[0],
                           FAR_LATENT_SPREADS, far[1])

    # ------------------------------------------------------------------ modes

    def mode_latents(self, vae: TrajectoryVAE, k: int | None = None) -> ModeLatents:
        """Per-mode mean latent (mean of its training behaviors' encoder means).

        Mode ids are the training episodes' labels (task strings ``"mode <id>: <name>"`` or
        ``meta/mode_labels.json``). Without labels (e.g. a dataset of language instructions) the modes are
        discovered by clustering the training episodes (:meth:`discover_modes`; ids are then cluster ids, and a
        warning says so). With gripper-segmented behaviors (several per episode) each mode gets one mean per
        phase, [n_phases, d_z], which ``set_latent`` uses in order as the phases advance (paper Eq. 12).
        ``k``: without labels, the number of modes to discover (None: found by :meth:`discover_modes`).
        """
        if len(self.mode) == 0:
            raise ValueError("mode_latents() needs the training behaviors: build the policy with dataset_meta "
                             "(lerobot-train does) or load a checkpoint")
        with torch.no_grad():
            z = self.latents(vae)
        if not self.labelled():
            try:
                found = self.discover_modes(vae, k=k)
            except ValueError as e:  # too few episodes to cluster: no k passed
                raise ValueError(f"mode_latents(): the training episodes carry no mode labels, and finding their modes "
                                 f"failed: {str(e).split('; pass k')[0]}. Label them (`lerobot-pdp label-modes DATASET`, "
                                 "then train), or choose the number of modes: policy.mode_latents(k=K) (its ids: "
                                 "`lerobot-pdp latent-map CKPT --k K`)") from e
            logger.warning("the training episodes carry no mode labels: mode_latents() returns the %d modes "
                           "discovered by clustering their behavior traces (policy.discover_modes(); ids are cluster "
                           "ids, see `lerobot-pdp latent-map`)%s", found.k,
                           ", and the taught modes" if len(self.taught) else "")
            taught = labelled_mode_latents(z, torch.where(self.is_taught(), self.mode, UNLABELED), self.phase(),
                                           self.config.mode_names)  # taught onto discovered clusters: their own ids
            return ModeLatents({**found.means, **taught}, taught.names, discovered=True)
        return labelled_mode_latents(z, self.mode, self.phase(), self.config.mode_names)

    def is_taught(self) -> Tensor:
        """[N] bool: the behaviours taught to the policy (the bank's last rows), not read from its training data."""
        return self.global_start == TAUGHT_START

    def labelled(self) -> bool:
        """Whether the training behaviours carry mode labels (else their modes are discovered clusters; taught
        modes have ids either way)."""
        return bool((self.mode[~self.is_taught()] >= 0).any())

    def discover_modes(self, vae: TrajectoryVAE, k: int | None = None, max_k: int | None = None, seed: int = 0,
                       space: str = "traces") -> DiscoveredModes:
        """Cluster the training episodes: the modes of a dataset without mode labels.

        Args:
            k: number of clusters; None finds it (``"traces"``: HDBSCAN; ``"latents"``: silhouette score
                over 2..``max_k``).
            max_k: ``space="latents"`` only: largest k tried; None = half the training episodes (at most
                ``modes.MAX_K_LIMIT``).
            seed: k-means seed of ``space="latents"`` (the result is deterministic for a given policy and seed).
            space: ``"traces"`` clusters the episodes by their behavior traces' soft-DTW divergences (the
                similarity the latents are trained to reproduce, without the distortion of a low-dimensional
                map); ``"latents"`` by their latents. See :mod:`lerobot_pdp.modes`.

        Taught modes (:meth:`append`) are no cluster's: they keep their own ids, past the clusters'.

        Returns:
            :class:`~lerobot_pdp.modes.DiscoveredModes`: ``labels`` (training episode index -> cluster id),
            ``means`` (cluster id -> mean latent, per phase for segmented policies), ``k``, silhouette scores,
            and the episodes that joined a cluster as outliers. The result is cached until the bank or the
            latents change.
        """
        if space not in SPACES:
            raise ValueError(f"space must be one of {SPACES}, got {space!r}")
        if len(self.episode) == 0:
            raise ValueError("discover_modes() needs the training behaviors: build the policy with dataset_meta "
                             "or load a checkpoint")
        n = int((~self.is_taught()).sum())  # the training behaviours (first): taught modes are no cluster's
        with torch.no_grad():
            z = self.latents(vae).cpu().numpy()[:n]
        key = (k, max_k, seed, space, hash(z.tobytes()))
        if self._discovered is None or self._discovered[0] != key:
            distances = None
            if space == "traces":  # delta^X, stored with the bank (one-hot latents store none: computed here)
                distances = self.distances.detach().cpu().numpy().astype(np.float64)[:n, :n]
                if self.config.latent_type == "onehot" or distances.shape != (len(z), len(z)):
                    cfg = self.config
                    distances = trace_distances(self.traces.cpu().numpy()[:n], cfg.sdtw_gamma, cfg.sdtw_normalize,
                                                progress=False)
            self._discovered = (key, discover(z, self.episode.cpu().numpy()[:n], self.phase().cpu().numpy()[:n], k,
                                              max_k, seed, distances))
        return self._discovered[1]
