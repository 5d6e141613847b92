"""The paper's evaluation protocol in one call: train every method with ``lerobot-train``, evaluate scenes 0-3
(the test split) or scene 0 and the env's validation scenes (``BenchmarkConfig.split="validation"``).

Every (method, seed) is trained and evaluated once; results are cached under ``out/`` so a rerun resumes
(an interrupted training from its last checkpoint).
The jobs live in their own modules: ``settings`` (budgets, methods), ``data`` (demonstrations),
``training`` (``lerobot-train``, checkpoint reuse, loading), ``evaluation`` (scenes 0-3), ``results``
(aggregation, merging, tables) and ``figures`` (drawn from the cached results).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from ..atomic import write_text_atomic
from ..envs.suite import SuiteEnv, get_suite_env
from ..folder_lock import hold_folder
from .data import check_run_env, ensure_dataset, ensure_demo
from .evaluation import evaluate_init_ablation, evaluate_method, evaluate_sweep
from .results import aggregate, frozen_record, results_markdown
from .settings import (
    ABLATIONS,
    CAMERAS,
    SETTINGS,
    SPACINGS,
    BenchmarkConfig,
    TrainSettings,
    check_split,
    frozen_for,
    methods_for,
)
from .training import train_method


def run_benchmark(cfg: BenchmarkConfig) -> dict[str, Any]:
    """Generate/reuse data, train every (method, seed), evaluate all scenes, write results and figures."""
    import lerobot_pdp.envs  # noqa: F401

    suite = get_suite_env(cfg.env)
    check_run_env(Path(cfg.out), suite)  # another env's run folder: refused before its data folder is written to
    full, quick = SETTINGS[suite.name]
    check_split(cfg.split, tuple(cfg.scenes), list(cfg.seeds))
    check_request(cfg, suite)
    if cfg.validate and cfg.split != "validation":
        raise ValueError("--validate chooses settings on the validation split only: add --split validation")
    if cfg.reuse_validation and not cfg.validate:
        raise ValueError("--reuse-validation reuses the candidates of an earlier --validate run: add --validate")
    if cfg.jobs < 1 or (cfg.jobs > 1 and not cfg.validate):
        raise ValueError(f"--jobs {cfg.jobs}: processes for --validate's candidates, a number >= 1 with --validate")
    if cfg.obs not in ("state", "images"):
        raise ValueError(f"obs must be 'state' or 'images', got {cfg.obs!r}")
    if cfg.obs == "images":
        camera = cfg.camera or CAMERAS.get(suite.name)
        if camera is None:
            raise ValueError(f"{suite.name} has no camera for the image benchmark; envs with one: {sorted(CAMERAS)}")
        suite = suite.with_camera(camera, cfg.image_size)
        cfg = replace(cfg, camera=camera)
        os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder would log its configuration per episode
    if cfg.teach:  # refused now, not after the training
        from .settings import teach_scenes

        teach_scenes(suite.name, cfg.split, cfg.scenes)
    if cfg.reuse_validation:  # a wrong file is refused now, not after hours of training
        from .validation import load_reuse_record

        load_reuse_record(cfg, suite.name)
    settings = quick if cfg.quick else full
    if cfg.episodes_per_mode is not None:
        settings = TrainSettings(**{**asdict(settings), "episodes_per_mode": cfg.episodes_per_mode})
    if cfg.lr is not None:
        if not cfg.lr > 0:
            raise ValueError(f"lr must be > 0, got {cfg.lr}")
        settings = replace(settings, lr=cfg.lr)
    if cfg.batch_size is not None:
        if cfg.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {cfg.batch_size}")
        settings = replace(settings, batch_size=cfg.batch_size)
    steps = cfg.steps if cfg.steps is not None else settings.steps
    user_sampler = cfg.inference_steps is not None or cfg.timestep_spacing is not None  # wins over FROZEN
    if cfg.inference_steps is None:
        cfg = replace(cfg, inference_steps=settings.inference_steps)
    if cfg.timestep_spacing is None:
        cfg = replace(cfg, timestep_spacing=settings.timestep_spacing)
    if cfg.timestep_spacing not in SPACINGS or (cfg.timestep_spacing == "even" and "dp" in cfg.methods):
        raise ValueError(f"timestep_spacing must be one of {SPACINGS} ('even', PDP's own sampler, without dp), "
                         f"got {cfg.timestep_spacing!r}")
    from ..configuration_pdp import PDPConfig

    k = PDPConfig.num_train_timesteps  # DP's matched config takes PDP's K too
    if not 1 <= cfg.inference_steps <= k:  # checked before any training, not at the first evaluation
        raise ValueError(f"inference_steps must be in 1..{k} (the diffusion steps K every method trains with), "
                         f"got {cfg.inference_steps}")
    check_device(cfg.device)
    frozen = frozen_record(suite.name, cfg)  # what this run samples and adapts with, whatever changes meanwhile
    all_methods = methods_for(suite, cfg.film, cfg.rec_reduction)
    names = list(dict.fromkeys(cfg.methods + (list(ABLATIONS) if cfg.ablations else [])))
    unknown = [n for n in names if n not in all_methods]
    if unknown:
        why = (" (with --obs images: mlp_bc and the ablations take state only)" if suite.camera_kwargs
               else " (vqbet needs --obs images: LeRobot's vqbet takes exactly one camera)" if "vqbet" in unknown
               else "")
        raise ValueError(f"unknown method(s) {unknown}; choose from {sorted(all_methods)}{why}")
    with hold_folder(cfg.out, "benchmark"):  # a second run into the same folder is refused, naming this one
        return _train_and_evaluate(cfg, suite, all_methods, names, settings, steps, frozen, user_sampler)


def _train_and_evaluate(cfg: BenchmarkConfig, suite: SuiteEnv, all_methods: dict[str, Any], names: list[str],
                        settings: TrainSettings, steps: int, frozen: dict[str, Any],
                        user_sampler: bool) -> dict[str, Any]:
    """``run_benchmark`` once its request is checked and its output folder held."""
    out = Path(cfg.out)
    dataset = ensure_dataset(suite, out, settings)
    demos = {s: ensure_demo(suite, out, s)[0] for s in cfg.scenes if s != 0}
    per_run: dict[str, dict[int, dict]] = {}
    init_abl: dict[int, dict] = {}
    ckpts: dict[tuple[str, int], Path] = {}
    method_cfgs: dict[str, BenchmarkConfig] = {}
    for name in names:
        method = all_methods[name]
        # what the validation split chose for this method (settings.FROZEN): its sampler, unless given on
        # the command line, is written into its checkpoints and used to evaluate; its adaptation settings
        chosen = frozen_for(suite.name, cfg.quick, name, cfg.obs)
        mcfg, msettings = cfg, settings
        if chosen.get("sampler") and not user_sampler:
            n, spacing = chosen["sampler"]
            mcfg = replace(cfg, inference_steps=int(n), timestep_spacing=spacing)
            msettings = replace(settings, inference_steps=int(n), timestep_spacing=spacing)
        method_cfgs[name] = mcfg
        for seed in cfg.seeds:
            run_dir = out / "runs" / name / f"seed{seed}"
            ckpt = train_method(method, dataset, run_dir, seed, msettings, steps, cfg.device)
            ckpts[(name, seed)] = ckpt
            per_run.setdefault(name, {})[seed] = evaluate_method(suite, method, ckpt, demos, mcfg, seed, run_dir,
                                                                 adapt_kwargs=chosen.get("adapt"))
            if cfg.ablations and name == "pdp":
                init_abl[seed] = evaluate_init_ablation(suite, ckpt, demos, mcfg, seed, run_dir)
    res = aggregate(suite.name, cfg, per_run, init_abl, settings, steps, frozen)
    if cfg.teach:
        from .teaching import run_teaching

        res["teach"] = run_teaching(suite, cfg, {n: all_methods[n] for n in names}, ckpts, dataset, demos, out,
                                    method_cfgs)
    if cfg.validate:
        from .validation import validate, validation_markdown

        runs = {name: {seed: out / "runs" / name / f"seed{seed}" for seed in cfg.seeds} for name in names}
        val = validate(cfg, suite, all_methods, runs, demos)
        write_text_atomic(out / "validation.md", validation_markdown(val))
        res["validation"] = {name: rec["chosen"] for name, rec in val["methods"].items()}
    write_text_atomic(out / "results.json", json.dumps(res, indent=1))
    write_text_atomic(out / "results.md", results_markdown(res))
    if cfg.figures:
        from .figures import write_figures

        seed = cfg.seeds[0]
        sweep = (evaluate_sweep(suite, ckpts[("pdp", seed)], out / "runs" / "pdp" / f"seed{seed}", method_cfgs["pdp"],
                                seed)
                 if ("pdp", seed) in ckpts else None)
        # relative to the output folder, so that a results folder can be moved or committed as it is
        res["figures"] = [str(p.relative_to(out)) for p in write_figures(suite, out, cfg, ckpts, sweep)]
        write_text_atomic(out / "results.json", json.dumps(res, indent=1))
    return res


def check_request(cfg: BenchmarkConfig, suite: SuiteEnv) -> None:
    """Refuse, before any dataset or training, what would train for nothing or report wrong numbers: no
    rollouts, no steps, a seed lerobot-train refuses, a scene listed twice (counted twice in the shifted
    average) or one the env does not ship."""
    from ..envs.scene import SceneError, load_scene

    out = Path(cfg.out)
    if (out.exists() and not out.is_dir()) or any(p.exists() and not p.is_dir() for p in out.parents):
        raise ValueError(f"--out {out}: {next(p for p in (out, *out.parents) if p.exists())} is a file; "
                         "give a folder (new, or a run's folder to resume)")
    for name, value in (("rollouts", cfg.rollouts), ("steps", cfg.steps), ("episodes_per_mode", cfg.episodes_per_mode)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")
    if not cfg.seeds:
        raise ValueError("seeds: give at least one training seed")
    for seed in cfg.seeds:
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
            raise ValueError(f"seeds must be whole numbers in 0..2**32-1 (lerobot-train's --seed), got {seed!r}")
    for name, values in (("seeds", list(cfg.seeds)), ("scenes", list(cfg.scenes))):
        twice = sorted({str(v) for v in values if values.count(v) > 1})
        if twice:
            raise ValueError(f"{name} lists {', '.join(twice)} more than once; each is run (and counted) once")
    for scene in cfg.scenes:
        try:
            load_scene(scene, suite.scene_key)
        except SceneError as e:
            raise ValueError(f"--scenes {scene}: {suite.name} ships no such scene ({e})") from None


def check_device(device: str) -> None:
    """Refuse a device that is not a torch device, or a CUDA device on a machine without one, before any
    dataset is generated or any method trained."""
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError as e:
        raise ValueError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:1, ...): {e}") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device!r}: this machine has no CUDA device (torch.cuda.is_available() is False)")
