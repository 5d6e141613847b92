"""The protocol's evaluation of one trained (method, seed): scene 0 steered per mode, scenes 1-3 (or the
validation scenes) after adapting to one demonstration, the latent-initialisation ablation; cached in the run
folder so a rerun resumes.

- Scene 0: rollouts spread evenly over the training modes; PDP conditions on each mode's mean latent,
  the baselines sample freely. Success, collision, mode coverage and entropy.
- Scenes 1-3: ONE successful demonstration in that scene is given (the scene's only feasible training
  mode, or the scene file's way-points). PDP fits z to it with every weight frozen; DP optimises its
  initial noise; BC fine-tunes its weights. Success and collision.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import write_text_atomic
from ..configuration_pdp import LEGACY_DEFAULTS
from ..envs.suite import SuiteEnv
from .data import demo_episode
from .rollouts import RolloutBatch, run_rollouts
from .settings import INIT_STEPS, BenchmarkConfig, Method, scene_seed_offset
from .training import load_policy


def checkpoint_sampler(ckpt: Path) -> tuple[int | None, str | None]:
    """The DDIM steps and grid a checkpoint samples with by itself, from one read of its config: PDP's
    fields (the legacy grid before the field existed, as PDPPolicy loads it), "leading" for LeRobot's
    diffusion (diffusers' default), (None, None) without a sampler."""
    saved = json.loads((Path(ckpt) / "config.json").read_text())
    if "num_inference_steps" not in saved:
        return None, None
    legacy = LEGACY_DEFAULTS["timestep_spacing"]
    spacing = saved.get("timestep_spacing", legacy) if saved.get("type") == "pdp" else "leading"
    return saved["num_inference_steps"], spacing


def sampler_of(ckpt: Path, cfg: BenchmarkConfig) -> dict[str, Any]:
    """What an evaluation of ``ckpt`` samples with under ``cfg`` (recorded in its cache file)."""
    steps, spacing = checkpoint_sampler(ckpt)
    if steps is None:
        return {"inference_steps": None}
    return {"inference_steps": int(cfg.inference_steps or steps), "timestep_spacing": cfg.timestep_spacing or spacing}


def cached_evaluation(path: Path, sampler: dict[str, Any], ckpt: Path, adapt_kwargs: dict[str, Any] | None = None
                      ) -> dict[str, Any] | None:
    """A cached evaluation made with the same sampler and adaptation settings (files from before a key
    existed were made with the checkpoint's own sampler and the default adaptation)."""
    if not path.is_file():
        return None
    cached = json.loads(path.read_text())
    steps, spacing = checkpoint_sampler(ckpt)
    same = (cached.get("inference_steps", steps) == sampler["inference_steps"]
            and cached.get("timestep_spacing", spacing) == sampler.get("timestep_spacing")
            and cached.get("adapt", {}) == (adapt_kwargs or {}))
    return cached if same else None


def _spread(n: int, k: int) -> list[int]:
    """n rollouts spread as evenly as possible over k modes."""
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def evaluate_scene0(suite: SuiteEnv, method: Method, policy, pre, post, n: int, seed: int,
                    modes: list[int] | None = None) -> RolloutBatch:
    """Scene 0: a steerable method steered to each mode's mean latent in turn (``modes``: these only), the
    ``n`` rollouts spread over them; another method's rollouts as it samples."""
    batch = RolloutBatch()
    if method.steerable:
        means = policy.mode_latents()
        modes = sorted(means) if modes is None else modes
        for m, count in zip(modes, _spread(n, len(modes)), strict=True):
            if count == 0:
                continue
            policy.set_latent(means[m])
            batch.extend(run_rollouts(suite, 0, policy, pre, post, count, seed + 97 * m, label=f"mode {m}"))
        policy.set_latent(None)
    else:
        batch.extend(run_rollouts(suite, 0, policy, pre, post, n, seed, label="sampled"))
    return batch


def adapt(method: Method, policy, pre, demo: dict[str, np.ndarray], seed: int, steps: int | None = None,
          init: str = "encoder", **kwargs: Any):
    """Adapt a policy to one demonstration the method's own way; returns (policy to roll out, info).

    ``kwargs``: the adaptation's settings besides the defaults (``steps``, ``lr``; PDP also ``lam``, ``objective``,
    ``noise`` and ``optimizer``), as the validation sweep varies them."""
    from .baselines import FixedNoisePolicy, adapt_dp_noise, finetune_bc

    if steps is not None:
        kwargs["steps"] = steps
    if method.adapt == "fit_latent":
        # segments="auto": a gripper-segmented policy fits one z per phase (paper Eq. 12)
        res = policy.fit_latent(demo, init=init, seed=seed, **kwargs)
        return policy, {"z": res.z.tolist(), "z_init": res.z_init.tolist(), "fit_loss": res.losses[-1:] or None,
                        "fit_error": res.fit_error, "fit_error_ratio": res.error_ratio}
    if method.adapt == "noise":
        noise = adapt_dp_noise(policy, pre, demo, seed=seed, **kwargs)
        return FixedNoisePolicy(policy, noise), {}
    if method.adapt == "finetune":
        return finetune_bc(policy, pre, demo, seed=seed, **kwargs), {}
    raise ValueError(f"unknown adaptation {method.adapt!r}")


def summarize_rollouts(batch: RolloutBatch, n_modes: int, with_modes: bool) -> dict[str, Any]:
    """Success, collision and count of a batch; with ``with_modes`` mode coverage / entropy and, for steered
    rollouts (label "mode <id>"), the share that landed in the mode they were given."""
    d: dict[str, Any] = {"success": batch.success_rate, "collision": batch.collision_rate,
                         "n": len(batch.results)}
    if with_modes:
        d.update(batch.mode_stats(n_modes))
        steered = [r for r in batch.results if r.label.startswith("mode ")]
        if steered:
            d["steer_accuracy"] = float(np.mean([r.mode == int(r.label.split()[1]) for r in steered]))
    return d


def evaluate_method(suite: SuiteEnv, method: Method, ckpt: Path, demos: dict[int | str, Path], cfg: BenchmarkConfig,
                    seed: int, run_dir: Path, adapt_kwargs: dict[str, Any] | None = None,
                    cache: Path | None = None) -> dict[str, Any]:
    """All scenes for one trained (method, seed); cached in ``cache`` (default ``run_dir/eval.json``).

    The cache is written after every scene, so an evaluation cut short goes on from the next scene when
    called again (each scene's rollouts and adaptation are seeded on their own: the same numbers as one
    uninterrupted run). ``adapt_kwargs``: adaptation settings besides the method's defaults (see :func:`adapt`)."""
    cache = cache or run_dir / "eval.json"
    traces_file = cache.with_name(cache.name.replace("eval", "traces", 1))
    adapt_kwargs = dict(adapt_kwargs or {})
    sampler = sampler_of(ckpt, cfg)
    cached = cached_evaluation(cache, sampler, ckpt, adapt_kwargs)
    if cached and cached.get("rollouts") == cfg.rollouts and set(map(str, cfg.scenes)) <= set(cached["scenes"]):
        print(f"[benchmark] {method.name} seed {seed}: evaluated already ({cache}), reused")
        return cached
    policy, pre, post = load_policy(ckpt, cfg.inference_steps, cfg.device, cfg.timestep_spacing)
    result: dict[str, Any] = {"method": method.name, "seed": seed, "rollouts": cfg.rollouts, **sampler,
                              "adapt": adapt_kwargs, "device": cfg.device, "scenes": {}}
    traces: dict[str, Any] = {}
    # scenes already done (on this device: the file records one device for all of its scenes)
    if cached and cached.get("rollouts") == cfg.rollouts and cached.get("device") == cfg.device and traces_file.is_file():
        old_traces = json.loads(traces_file.read_text())
        keep = [str(s) for s in cfg.scenes if str(s) in cached["scenes"] and str(s) in old_traces]
        result["scenes"] = {k: cached["scenes"][k] for k in keep}
        traces = {k: old_traces[k] for k in keep}
    cache.parent.mkdir(parents=True, exist_ok=True)
    for scene in cfg.scenes:
        if str(scene) in result["scenes"]:
            continue
        t0 = time.time()
        if scene == 0:
            batch = evaluate_scene0(suite, method, policy, pre, post, cfg.rollouts, seed * 10_000)
            summary = summarize_rollouts(batch, suite.n_modes, with_modes=True)
        else:
            print(f"[benchmark] {method.name} seed {seed} scene {scene}: adapting to its demonstration "
                  f"({method.adapt})", flush=True)  # a fit takes tens of seconds before the rollouts' bar
            demo = demo_episode(demos[scene])
            actor, info = adapt(method, copy.deepcopy(policy) if method.adapt == "finetune" else policy, pre, demo, seed,
                                **adapt_kwargs)
            batch = run_rollouts(suite, scene, actor, pre, post, cfg.rollouts,
                                 seed * 10_000 + scene_seed_offset(scene), label=f"scene {scene}")
            summary = {**summarize_rollouts(batch, suite.n_modes, with_modes=False), **info}
            if method.adapt == "fit_latent":
                policy.set_latent(None)
        summary["seconds"] = time.time() - t0
        result["scenes"][str(scene)] = summary
        traces[str(scene)] = [{"trace": r.trace.tolist(), "success": r.success, "label": r.label, "mode": r.mode}
                              for r in batch.results]
        print(f"[benchmark] {method.name} seed {seed} scene {scene}: success {summary['success']:.0%}"
              f" collision {summary['collision']:.0%}")
        # traces first: a cache never names a scene whose traces are missing
        write_text_atomic(traces_file, json.dumps(traces))
        write_text_atomic(cache, json.dumps(result, indent=1))
    if method.policy_type == "pdp":
        result["latents"] = {k: v.tolist() for k, v in policy.behavior_table().items()}
    result["scenes"] = {str(s): result["scenes"][str(s)] for s in cfg.scenes}  # the split's order
    traces = {str(s): traces[str(s)] for s in cfg.scenes}
    write_text_atomic(traces_file, json.dumps(traces))
    write_text_atomic(cache, json.dumps(result, indent=1))
    return result


def evaluate_init_ablation(suite: SuiteEnv, ckpt: Path, demos: dict[int | str, Path], cfg: BenchmarkConfig, seed: int,
                           run_dir: Path) -> dict[str, Any]:
    """Warm (encoder) vs random initialisation of z at 0 / 10 / 100 fitting steps, scenes 1-3.

    ``{"encoder@0": mean success over the shifted scenes, ..., "per_scene": {"encoder@0": {"1": rate, ...}}}``;
    the per-scene rates say *where* an initialisation wins or loses, which the mean hides."""
    cache = run_dir / "init_ablation.json"
    sampler = sampler_of(ckpt, cfg)
    # what the rates depend on besides the sampler: a cache of other rollouts or scenes is redone
    design = {"rollouts": cfg.rollouts, "scenes": [str(s) for s in cfg.scenes if s != 0]}
    cached = cached_evaluation(cache, sampler, ckpt)
    if cached and all(cached.get(k) == v for k, v in design.items()):
        return {k: v for k, v in cached.items() if k not in sampler and k not in design and k != "device"}
    policy, pre, post = load_policy(ckpt, cfg.inference_steps, cfg.device, cfg.timestep_spacing)
    method = Method("pdp", "pdp")
    out: dict[str, Any] = {}
    per_scene: dict[str, dict[str, float]] = {}
    for init in ("encoder", "random"):
        for steps in INIT_STEPS:
            key, rates = f"{init}@{steps}", {}
            for scene in [s for s in cfg.scenes if s != 0]:
                demo = demo_episode(demos[scene])
                actor, _ = adapt(method, policy, pre, demo, seed, steps=steps, init=init)
                batch = run_rollouts(suite, scene, actor, pre, post, cfg.rollouts,
                                     seed * 10_000 + scene_seed_offset(scene))
                rates[str(scene)] = batch.success_rate
            out[key] = float(np.mean(list(rates.values()))) if rates else None
            per_scene[key] = rates
            print(f"[benchmark] init {init} steps {steps}: success {out[key]} per scene {rates}")
    policy.set_latent(None)
    out["per_scene"] = per_scene
    write_text_atomic(cache, json.dumps({**out, **sampler, **design, "device": cfg.device}, indent=1))
    return out


def evaluate_sweep(suite: SuiteEnv, ckpt: Path, run_dir: Path, cfg: BenchmarkConfig, seed: int, n: int = 7
                   ) -> dict[str, Any] | None:
    """Latents between the two farthest-apart mode means, along a linear and an elliptical path, one scene-0
    rollout each: what the interpolation figure shows. Cached in ``run_dir/sweep.json``; None for a policy
    without a latent or with fewer than two modes."""
    cache = run_dir / "sweep.json"
    sampler = sampler_of(ckpt, cfg)
    cached = cached_evaluation(cache, sampler, ckpt)
    if cached and cached.get("n") == n and cached.get("seed") == seed:
        return cached
    policy, pre, post = load_policy(ckpt, cfg.inference_steps, cfg.device, cfg.timestep_spacing)
    if policy.config.latent_conditioning == "none":
        return None
    means = policy.mode_latents()
    keys = sorted(means)
    if len(keys) < 2:
        return None
    # the two farthest-apart mode means: the sweep crosses the whole manifold
    pairs = [(a, b) for a in keys for b in keys if a < b]
    a, b = max(pairs, key=lambda ab: float((means[ab[0]] - means[ab[1]]).norm()))
    paths: dict[str, Any] = {}
    for path in ("linear", "elliptical"):
        zs = policy.interpolate(means[a], means[b], n, path=path)
        rollouts = []
        for k, z in enumerate(zs):
            policy.set_latent(z)
            r = run_rollouts(suite, 0, policy, pre, post, 1, seed + k).results[0]
            rollouts.append({"trace": r.trace.tolist(), "success": r.success})
        policy.set_latent(None)
        paths[path] = {"z": zs.tolist(), "rollouts": rollouts}
    out = {**sampler, "n": n, "seed": seed, "device": cfg.device, "modes": [a, b], "paths": paths,
           "behaviors": {k: v.tolist() for k, v in policy.behavior_table().items()}}
    write_text_atomic(cache, json.dumps(out))
    return out
