"""Teaching a new mode: one demonstration of a route no latent makes becomes a behaviour of the policy.

Fitting z (``adaptation.py``) moves nothing but the latent, so it can only pick among the behaviours the
denoiser already knows. When the fit's error ratio says the route is out of reach, :func:`teach_new_mode` adds the
demonstration as a new mode instead:

- **Its latent** is the frozen encoder's mean of its trace (one per phase for segmented policies), or with
  ``latent="geometry"`` where the encoder's geometry term puts it against the training latents: the encoder
  and decoder (phi, psi) do not move, so every training behaviour keeps its latent and each old mode is
  selected by the latent it had. The bank keeps the new latent (``taught_latents`` in the checkpoint).
- **It joins the behaviour bank** as mode ``max + 1``, without labels past the discovered clusters (its trace,
  frame ranges, soft-DTW distances and name; ``BehaviorBank.append``), so ``mode_latents()``, ``latent-map``,
  ``--policy.steer_mode`` and a steer file know it.
- **The denoiser theta alone is fine-tuned** (the observation encoder too is frozen): a fixed share of each
  batch is the demonstration's windows at the new latent, the rest *rehearses* the training windows at their
  own latents, and the demonstrations of modes taught before at theirs (the policy keeps them:
  :mod:`.taught_demos`), so the old modes keep acting as before. The loss is the training loss L_DP.

LeRobot's training loop is not reused for it: it samples one dataset uniformly and trains every parameter of
the optimizer groups, while teaching needs a fixed demonstration share and all but theta frozen.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.utils.constants import ACTION
from torch import Tensor

from .adaptation import demonstration_traces, encode_demonstration, warn_unreachable_actions
from .behavior import UNLABELED, read_training_behaviors, training_behavior_keys
from .chunk_windows import DemoWindows
from .configuration_pdp import PDPConfig
from .console import latent_text, loss_ends_text
from .demonstration import Episode, check_recording, demonstration_source, read_demonstration
from .diffusion import diffusion_loss
from .episodes import read_episode_frames, read_episodes
from .teach_defaults import (  # noqa: F401  (re-exported)
    TEACH_BATCH_SIZE,
    TEACH_DEMO_SHARE,
    TEACH_LATENT,
    TEACH_LATENTS,
    TEACH_LR,
    TEACH_STEPS,
    check_mode_name,
    check_teach_settings,
)

logger = logging.getLogger(__name__)


@dataclass
class TeachResult:
    """What :func:`teach` did: the new mode, its latent(s), the loss history and the windows it trained on."""

    mode: int  # the new mode id
    z: Tensor  # its latent(s), [M, d_z] (one per phase)
    losses: list[float] = field(default_factory=list)  # L_DP per step (demonstration and rehearsal windows)
    steps: int = 0
    demo_windows: int = 0
    rehearsal_windows: int = 0
    # distance from the new latent to the nearest training latent, in RMS standard deviations of them
    nearest_spreads: float = float("nan")
    seconds: float = 0.0
    settings: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:  # a summary: the dataclass's would print every step's loss
        loss = loss_ends_text(self.losses)
        return (f"TeachResult(mode={self.mode}, z={[[round(x, 4) for x in r] for r in self.z.tolist()]}, "
                f"steps={self.steps}, loss {loss}, windows {self.demo_windows} demo + {self.rehearsal_windows} "
                f"rehearsal, nearest_spreads={self.nearest_spreads:.3g}, seconds={self.seconds:.1f})")


@dataclass
class TrainingRehearsal:
    """The training dataset read, checked and cut into rehearsal windows once, for several teachings of one policy
    (:func:`read_rehearsal`): the windows and their latents do not change while teaching (encoder and observation
    encoder are frozen, the training behaviours keep their latents), and reading them decodes every camera frame."""

    windows: DemoWindows
    latents: Tensor  # [N, d_z], each window's behaviour latent
    policy: Any  # the policy it was read for: its bank is what the dataset was checked against
    root: Path  # the dataset's folder (teaching.json names it)


def read_rehearsal(policy: Any, training_data: str | Path) -> TrainingRehearsal:
    """Check that ``training_data`` is ``policy``'s training dataset and read its rehearsal windows; pass the result
    as ``training_data`` to :func:`teach_new_mode` to teach the policy several modes with one read."""
    episodes = check_training_data(policy, training_data)
    windows, latents = rehearsal_windows(policy, training_data, episodes)
    return TrainingRehearsal(windows, latents, policy, Path(training_data))


def teach_new_mode(policy: Any, episode: Episode, training_data: str | Path | TrainingRehearsal,
                   steps: int = TEACH_STEPS, lr: float = TEACH_LR, demo_share: float = TEACH_DEMO_SHARE,
                   batch_size: int = TEACH_BATCH_SIZE, seed: int = 0, name: str | None = None,
                   latent: str = TEACH_LATENT, progress: bool = True) -> TeachResult:
    """Add one demonstration to ``policy`` (a ``PDPPolicy``, changed in place) as a new mode; see the module.

    Args:
        episode: the demonstration, a ``(dataset folder, episode index)`` pair or a dict of arrays.
        training_data: the folder of the dataset the policy was trained on (its behaviour bank must match), or
            its :func:`read_rehearsal` for this policy (several teachings, one read).
        steps, lr, batch_size: Adam steps on theta, their step size, windows per step.
        demo_share: the demonstration's share of each batch; the rest rehearses the training windows.
        name: the new mode's name (default: where the demonstration came from).
        latent: where the new mode's latent goes: ``"encoder"``, the encoder's mean of the demonstration, or
            ``"geometry"``, from there to where the geometry term the encoder was trained with puts it
            against the fixed training latents (:func:`geometric_latent`).
    """
    model, cfg = policy.model, policy.config
    check_teach_settings(steps, lr, demo_share, batch_size)
    check_mode_name(name)
    if latent not in TEACH_LATENTS:
        raise ValueError(f"teach: latent must be one of {TEACH_LATENTS}, got {latent!r}")
    if cfg.latent_type != "continuous":
        raise ValueError(f"teach needs a continuous latent; this policy's latent_type is {cfg.latent_type!r}")
    if model.bank.labelled() and bool((model.bank.mode[~model.bank.is_taught()] == UNLABELED).any()):
        raise ValueError("teach needs every training episode mode-labelled, or none (then the modes are "
                         "discovered clusters and the new mode's id follows theirs): some episodes of the training "
                         "dataset carry a label and some do not; label them all (lerobot-pdp label-modes) and train "
                         "again")
    name = name or _demo_name(episode)
    same = sorted(int(k) for k, v in (cfg.mode_names or {}).items() if v == name)
    if same:  # steering by that name would reach the old mode
        raise ValueError(f"teach: mode {same[0]} is already named {name!r}; give the new mode another name")
    prepared = training_data if isinstance(training_data, TrainingRehearsal) else None
    if prepared is not None and prepared.policy is not policy:
        raise ValueError("teach: the TrainingRehearsal given was read for another policy (read_rehearsal(policy, ...))")
    episodes = check_training_data(policy, training_data) if prepared is None else None
    t0 = time.perf_counter()
    demo = read_demonstration(episode, cfg, policy.action_dim, "auto", need_action=True)
    warn_unreachable_actions(cfg, policy.stats, demo, what="teach")  # a taught mode's chunks are clipped too
    demo_win = policy._demo_windows(demo)
    z_new = encode_demonstration(model, cfg, demo)  # continuous: the frozen encoder's mean per phase
    with torch.no_grad():
        z_bank = model.behavior_latents().cpu()
    if prepared is None:
        rehearsal, z_old = rehearsal_windows(policy, training_data, episodes)
    else:
        rehearsal, z_old = prepared.windows, prepared.latents
    taught = taught_windows(policy, z_bank)  # the modes taught before, which the training data does not hold
    with restored_on_failure(policy):  # Ctrl-C or an error from here on leaves the policy as it was
        mode = model.bank.append(demonstration_traces(cfg, demo), demo.segments, name, z_new, new_mode_id(policy))
        model.bank.taught_demos[mode] = demo  # rehearsed when the policy is taught again (taught_demos.py)
        warn_if_known_route(model.bank, len(z_bank), mode)
        if latent == "geometry":
            delta = model.bank.distances[len(z_bank):, : len(z_bank)].detach().cpu()
            z_new = geometric_latent(z_new, z_bank, delta, float(model.bank.kappa))
            model.bank.place_taught(z_new)
        spread = float(z_bank.var(0).mean().sqrt()) if len(z_bank) > 1 else float("nan")  # as set_latent's warning
        nearest = float(torch.cdist(z_new, z_bank).min()) / spread
        losses = _finetune(model, cfg, demo_win, z_new[demo_win.segment], rehearsal, z_old, steps, lr, demo_share,
                           batch_size, seed, progress, taught)
    policy.steering.activate(None)
    n_rehearsed = len(rehearsal.actions) + (len(taught[0].actions) if taught is not None else 0)
    result = TeachResult(mode, z_new, losses, steps, len(demo_win.actions), n_rehearsed, nearest,
                         time.perf_counter() - t0, {"steps": steps, "lr": lr, "demo_share": demo_share,
                                                    "batch_size": batch_size, "seed": seed, "latent": latent})
    data = prepared.root if prepared is not None else Path(training_data)
    model.bank.teachings[mode] = teaching_record(policy, episode, data, result, name)  # saved as teaching.json
    logger.info("taught mode %d (%s) in %.1f s: latent %s, %.1f spreads from the nearest training latent; L_DP "
                "%.4f -> %.4f", mode, cfg.mode_names.get(str(mode)), result.seconds, latent_text(z_new), nearest,
                _mean(losses[:20]), _mean(losses[-20:]))
    return result


@contextlib.contextmanager
def restored_on_failure(policy: Any) -> Iterator[None]:
    """Put ``policy`` back as it was when the block fails or is interrupted (Ctrl-C in a notebook): the behaviour
    bank (the new mode, its trace, distances and demonstration), the mode names and the denoiser's weights; then
    the error goes on. Teaching changes nothing else of the policy before it succeeds."""
    model, cfg = policy.model, policy.config
    bank = model.bank.snapshot()
    names = dict(cfg.mode_names) if cfg.mode_names is not None else None
    weights = {k: v.clone() for k, v in model.denoiser.state_dict().items()}
    try:
        yield
    except BaseException:
        model.bank.restore(bank)
        cfg.mode_names = names
        with torch.no_grad():
            model.denoiser.load_state_dict(weights)
        logger.warning("teach stopped before it ended: the policy is as it was before teach (no mode added, weights "
                       "unchanged)")
        raise


def teaching_record(policy: Any, episode: Episode, data: Path, result: TeachResult, name: str) -> dict[str, Any]:
    """What ``teaching.json`` records of one teaching: the base (the folder ``policy`` was loaded from), the
    demonstration, the rehearsal data, the new mode, the settings, the mean loss over the first and the last
    ``loss_window`` steps (50, or half a shorter run), the time, the date."""
    base = getattr(policy, "_loaded_from", None)
    demo = demonstration_source(episode)
    n = max(1, min(50, len(result.losses) // 2))  # a short run: two halves, not one window counted twice
    head, tail = result.losses[:n], result.losses[-n:]
    return {"source": "teach", "base_checkpoint": None if base is None else str(Path(base).resolve()),
            "demonstration": demo, "training_data": str(data.resolve()), "mode": result.mode, "mode_name": name,
            "latent": result.z.tolist(), "nearest_training_latent_spreads": result.nearest_spreads,
            "settings": result.settings, "loss_first": _mean(head), "loss_last": _mean(tail), "loss_window": n,
            "demo_windows": result.demo_windows, "rehearsal_windows": result.rehearsal_windows,
            "seconds": round(result.seconds, 1),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}


def new_mode_id(policy: Any) -> int:
    """The id of the next taught mode: one past the last mode id, where labelled training modes or the modes taught
    before end; without labels, past the clusters ``mode_latents()`` finds too (and past any taught before)."""
    bank = policy.model.bank
    last = int(bank.mode.max()) if len(bank.mode) else -1
    if not bank.labelled():
        last = max(last, bank.discover_modes(policy.model.vae).k - 1)
    return last + 1


def warn_if_known_route(bank: Any, n_old: int, mode: int) -> None:
    """Warn (before the fine-tuning's minutes) when the demonstration's trace is as close to a behaviour the policy
    has as its training behaviours are to their nearest neighbour: a route it knows, which a fit reaches without a
    new mode. Told by soft-DTW divergences (delta^X), not latents: the encoder may put a new route near an old one."""
    d = bank.distances.detach().cpu().double()
    if n_old < 2 or len(d) <= n_old:
        return
    old = d[:n_old, :n_old] + torch.diag(torch.full((n_old,), math.inf, dtype=d.dtype))
    typical = float(old.min(1).values.median())  # a behaviour to its nearest other one
    new = d[n_old:, :n_old]  # [phases, old]
    nearest = new.min(1)
    if bool((nearest.values <= typical).all()):
        j = int(nearest.indices[0])
        label = f" (mode {int(bank.mode[j])})" if int(bank.mode[j]) >= 0 else ""
        logger.warning("teach: the demonstration's trace is as close to training episode %d%s as training "
                       "behaviours are to their nearest neighbour (soft-DTW %.3g, typical %.3g): the policy may know "
                       "this route already; a fit (lerobot-pdp adapt) reaches a known route without teaching mode %d",
                       int(bank.episode[j]), label, float(nearest.values.max()), typical, mode)


def geometric_latent(z0: Tensor, z_old: Tensor, delta: Tensor, kappa: float, steps: int = 500,
                     lr: float = 0.05) -> Tensor:
    """The latents [M, d_z] that best satisfy the geometry term the encoder was trained with,
    ``sum_j (|z - z_j| - kappa * delta_j)^2``, against the fixed training latents ``z_old`` [N, d_z] (an
    out-of-sample step of metric MDS), from ``z0``; ``delta`` [M, N]: the new traces' soft-DTW divergences to
    the training traces. Why: an encoder trained on a few hundred traces extrapolates poorly to a route unlike
    them, and may put it next to a training latent whose behaviour it does not share."""
    target = kappa * delta.float()
    with torch.inference_mode(False), torch.enable_grad():
        z = z0.detach().clone().float().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        for _ in range(steps):
            d = (z[:, None] - z_old[None].float()).pow(2).sum(-1).add(1e-12).sqrt()
            loss = (d - target).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    return z.detach()


def _mean(xs: list[float]) -> float:
    return float(np.mean(xs)) if xs else float("nan")


def _demo_name(episode: Episode) -> str:
    source = demonstration_source(episode)
    return f"taught: episode {source['episode']} of {Path(source['dataset']).name}" if "dataset" in source else "taught"


def check_training_data(policy: Any, root: str | Path) -> dict[int, dict]:
    """Refuse a dataset that is not the one ``policy`` was trained on: its behaviour traces (one per episode, or
    per phase) must be the ones the checkpoint's behaviour bank holds. Returns its episodes as read (the columns
    the traces and the rehearsal windows need), so that teaching reads the files once."""
    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset folder (no meta/info.json): give the dataset the "
                                "policy was trained on")
    model, cfg = policy.model, policy.config
    check_recording(root, 0, {k: tuple(ft.shape) for k, ft in cfg.condition_features.items()},
                    what="training dataset", advice="Give the dataset the policy was trained on (--data)",
                    fps=cfg.dataset_fps, names=cfg.dataset_feature_names)
    features = json.loads((root / "meta" / "info.json").read_text()).get("features", {})
    # the episodes it trained on (lerobot-train's --dataset.episodes), not the held-out ones
    episodes = read_episodes(root, list(dict.fromkeys([*training_behavior_keys(cfg, features), *_rehearsal_keys(cfg)])),
                             cfg.dataset_episodes)
    found = read_training_behaviors(cfg, root, features, episodes)
    bank = model.bank.traces.detach().cpu().numpy()
    taught = model.bank.is_taught().cpu().numpy()
    n_bank = int((~taught).sum())
    if len(found) != n_bank or not np.array_equal(found.episode_index, model.bank.episode.cpu().numpy()[~taught]):
        raise ValueError(f"{root} is not the policy's training dataset: it holds {len(found)} behaviours of episodes "
                         f"{_span(found.episode_index)}, the checkpoint's behaviour bank {n_bank} of episodes "
                         f"{_span(model.bank.episode.cpu().numpy()[~taught])}")
    diff = np.abs(found.traces.astype(np.float32) - bank[~taught]).reshape(len(found), -1).max(1)
    if (diff > 1e-4).any():
        ep = int(found.episode_index[int(np.argmax(diff > 1e-4))])
        raise ValueError(f"{root} is not the policy's training dataset: episode {ep}'s behaviour trace differs from "
                         f"the one in the checkpoint's behaviour bank (by up to {float(diff.max()):.3g})")
    return episodes


def _span(episodes: np.ndarray) -> str:
    return f"{int(episodes.min())}..{int(episodes.max())}" if len(episodes) else "(none)"


def _rehearsal_keys(cfg: PDPConfig) -> list[str]:
    """The non-camera columns a rehearsal window needs (cameras are read per episode as frames)."""
    return [k for k in dict.fromkeys([*cfg.condition_features, ACTION, cfg.trace_key]) if k not in cfg.image_features]


def rehearsal_windows(policy: Any, root: str | Path,
                      episodes: dict[int, dict] | None = None) -> tuple[DemoWindows, Tensor]:
    """Every training-style window of the training dataset at ``root`` (normalised, split into the phases the
    behaviour bank holds), and the latent of the behaviour each window belongs to, [N, d_z]. ``episodes``: the
    dataset's episodes already read (:func:`check_training_data` returns them)."""
    model, cfg = policy.model, policy.config
    cameras = [k for k in cfg.condition_features if k in cfg.image_features]
    if episodes is None:
        episodes = read_episodes(root, _rehearsal_keys(cfg), cfg.dataset_episodes)
    with torch.no_grad():
        z_bank = model.behavior_latents().detach().cpu()
    bank_ep = model.bank.episode.cpu().numpy()
    bank_start, bank_end = model.bank.start.cpu().numpy(), model.bank.end.cpu().numpy()
    parts, zs = [], []
    for ep, arrays in episodes.items():
        ids = np.flatnonzero(bank_ep == ep)
        ids = ids[np.argsort(bank_start[ids])]
        arrays = {**arrays, **read_episode_frames(root, ep, cameras)} if cameras else arrays
        segments = [(int(bank_start[i]), int(bank_end[i])) for i in ids]
        demo = read_demonstration(arrays, cfg, policy.action_dim, segments, need_action=True)
        w = policy._demo_windows(demo)
        parts.append(w)
        zs.append(z_bank[torch.as_tensor(ids)][w.segment])
    return DemoWindows.concat(parts), torch.cat(zs)


def taught_windows(policy: Any, z_bank: Tensor) -> tuple[DemoWindows, Tensor] | None:
    """The windows of every mode taught before and their taught latent(s) (rows of ``z_bank``, the bank's latents);
    None when the policy keeps none. A mode taught by a release that did not keep its demonstration cannot be
    rehearsed: said in a warning."""
    bank = policy.model.bank
    missing = bank.unrehearsable_modes()
    if missing:
        logger.warning("teach: taught mode(s) %s were taught by a release that did not keep their demonstrations: "
                       "they are not rehearsed, and this teaching may change how they act (teach the base checkpoint "
                       "each demonstration again to keep them all)", missing)
    if not bank.taught_demos:
        return None
    parts, zs = [], []
    for mode, demo in sorted(bank.taught_demos.items()):
        rows = torch.nonzero(bank.mode.cpu() == mode).flatten()  # one behaviour per phase, in order
        w = policy._demo_windows(demo)
        parts.append(w)
        zs.append(z_bank[rows][w.segment.cpu()])
    return DemoWindows.concat(parts), torch.cat(zs)


def _finetune(model: Any, cfg: PDPConfig, demo: DemoWindows, z_demo: Tensor, rehearsal: DemoWindows, z_old: Tensor,
              steps: int, lr: float, demo_share: float, batch_size: int, seed: int, progress: bool,
              taught: tuple[DemoWindows, Tensor] | None = None) -> list[float]:
    """Adam on the denoiser alone: each batch ``demo_share`` demonstration windows at their new latent, as many
    windows of the modes taught before (``taught``) at theirs, the rest training windows at their own, the training
    loss L_DP; gradient norm clipped as in training."""
    device = model.device
    n_demo = max(1, round(demo_share * batch_size))
    # The modes taught before, together, as many windows as the new demonstration: drawn among the training windows
    # instead, one taught demonstration beside 240 training episodes was forgotten (avoiding val4: 90 % -> 0 % after
    # val5 was taught; scripts/teach_again.py).
    n_taught = min(n_demo, batch_size - n_demo) if taught is not None else 0
    pools = [(demo, z_demo, n_demo), *([(*taught, n_taught)] if n_taught else []),
             (rehearsal, z_old, batch_size - n_demo - n_taught)]
    pools = [pool for pool in pools if pool[2] > 0]
    params = list(model.denoiser.parameters())
    opt = torch.optim.Adam(params, lr=lr)
    g = torch.Generator().manual_seed(int(seed))
    mask_pad = cfg.do_mask_loss_for_padding
    losses: list[float] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="teach", unit="step")
    was_training = model.denoiser.training
    model.denoiser.train()
    try:
        # the seed reaches the draws on the model's device too (CUDA's generator), and leaves the caller's as found
        on = torch.device(device)
        cuda = [on.index or 0] if on.type == "cuda" else []
        with torch.inference_mode(False), torch.enable_grad(), torch.random.fork_rng(devices=cuda):
            torch.manual_seed(int(seed))
            for _ in range(steps):
                picks = [(w, z, torch.randint(0, len(w.actions), (n,), generator=g)) for w, z, n in pools]
                obs = torch.cat([w.obs_cond[i].to(device) for w, _, i in picks])  # pools may sit on the CPU
                actions = torch.cat([w.actions[i].to(device) for w, _, i in picks])
                is_pad = torch.cat([w.is_pad[i].to(device) for w, _, i in picks])
                z = torch.cat([zp[i].to(device) for _, zp, i in picks])
                eps = torch.randn_like(actions)
                k = torch.randint(0, cfg.num_train_timesteps, (len(actions),), device=device)
                pred = model.denoiser(model.noise_schedule.add_noise(actions, eps, k), k, obs, z)
                loss = diffusion_loss(pred, eps, is_pad if mask_pad else None)
                value = float(loss.detach())
                if not math.isfinite(value):
                    raise FloatingPointError(f"teach: the loss became non-finite at step {len(losses) + 1} ({value}); "
                                             "the policy is left as it was before teach. Lower the lr")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, cfg.optimizer_grad_clip_norm)
                opt.step()
                losses.append(value)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{losses[-1]:.4f}", refresh=False)
    finally:  # also when the loss turns non-finite: the policy's mode and the console are left as found
        opt.zero_grad(set_to_none=True)  # no gradient left on the denoiser's weights
        model.denoiser.train(was_training)
        if bar is not None:
            bar.close()
    return losses
