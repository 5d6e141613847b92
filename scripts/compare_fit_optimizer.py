"""PDP's latent fit (Adam, the mean of its last iterates) against the paper's plain gradient steps on z, on the
validation split.

    .venv/bin/python scripts/compare_fit_optimizer.py runs/reach_around_val --lr 0.3 1 3 \\
        --out docs/results/reach-around/validation_fit_optimizer.json

Takes a finished ``lerobot-pdp benchmark --split validation`` folder (its PDP checkpoints and the validation
scenes' demonstrations). Every candidate adapts as that run's PDP does (the frozen adaptation
its results.json records: objective, chunk noises) with only the optimizer changed: Adam at ``fit_lr`` first (the
run's own evaluation), then plain steps ``z <- z - lr * grad`` at each ``--lr`` (their step size is on the
gradient's scale, not Adam's, so it gets a sweep of its own; the record holds the gradient's norm at each
demonstration's encoder latent, ``--grad-draws`` draws of the fit's batch, to centre that sweep). Scored on the validation scenes over every seed and
chosen by the validation rule (Adam stays unless beaten by more than one binomial standard error). Each
candidate's rollouts are cached in the run folder (``validation/eval_<tag>.json``), so a cut run goes on.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a finished `lerobot-pdp benchmark --split validation` folder")
    ap.add_argument("--lr", type=float, nargs="+", required=True, help="step sizes of the plain gradient steps")
    ap.add_argument("--out", type=Path, required=True, help="the record (JSON)")
    ap.add_argument("--grad-draws", type=int, default=4, help="batches drawn for each gradient norm (default 4)")
    args = ap.parse_args(argv)

    import lerobot_pdp.envs  # noqa: F401  (registers the suite)
    from lerobot_pdp.atomic import write_text_atomic
    from lerobot_pdp.benchmark.data import ensure_demo
    from lerobot_pdp.benchmark.settings import SETTINGS, BenchmarkConfig, frozen_for, methods_for
    from lerobot_pdp.benchmark.training import load_policy
    from lerobot_pdp.benchmark.validation import _evaluate, _score, candidate_tag, choose
    from lerobot_pdp.envs.suite import get_suite_env

    results_file = args.run / "results.json"
    if not results_file.is_file():
        ap.error(f"no results file at {results_file}: give a finished `benchmark --split validation` folder")
    res = json.loads(results_file.read_text())
    if res.get("split") != "validation" or res.get("observation") or "pdp" not in res.get("methods", {}):
        ap.error(f"{results_file}: a {res.get('split', 'test')!r} run of {sorted(res.get('methods', {}))}; "
                 "fitting settings are compared on a state-only validation run of pdp")
    suite = get_suite_env(res["env"])
    seeds = res["methods"]["pdp"]["seeds"]
    scenes = [s for s in res["scenes"] if s != 0]
    cfg = BenchmarkConfig(env=suite.name, out=args.run, seeds=seeds, rollouts=res["rollouts"], quick=res["quick"],
                          scenes=tuple(scenes), split="validation", film=res.get("film"),
                          rec_reduction=res.get("rec_reduction", "mean"))
    method = methods_for(suite, cfg.film, cfg.rec_reduction)["pdp"]
    # what the run itself sampled and adapted with (results.json's "frozen"; older runs: the settings now)
    chosen = (res["frozen"]["methods"].get("pdp", {}) if "frozen" in res
              else frozen_for(suite.name, cfg.quick, "pdp"))
    settings = SETTINGS[suite.name][1 if cfg.quick else 0]
    sampler = tuple(chosen.get("sampler") or (settings.inference_steps, settings.timestep_spacing))
    base = dict(chosen.get("adapt", {}))
    runs = {seed: args.run / "runs" / "pdp" / f"seed{seed}" for seed in seeds}
    demos = {s: ensure_demo(suite, args.run, s)[0] for s in scenes}
    candidates = [("adam", base), *[(f"gradient lr {lr:g}", {**base, "optimizer": "gradient", "lr": lr})
                                    for lr in args.lr]]
    policy = load_policy(runs[seeds[0]] / "pretrained_model")[0]
    norms = {str(s): gradient_norms(policy, demos[s], base, args.grad_draws) for s in scenes}
    print(f"gradient norms at the encoder's latent (seed {seeds[0]}): {norms}", flush=True)
    rows = []
    for name, adapt in candidates:
        evals = _evaluate(suite, method, runs, demos, cfg, sampler, adapt, scenes)
        rows.append({"candidate": name, "tag": candidate_tag(sampler, adapt), "adapt": adapt,
                     "score": _score(evals, scenes),
                     "success": {str(s): [e["scenes"][str(s)]["success"] for e in evals] for s in scenes}})
        print(f"{name}: {rows[-1]['score']:.1%}  " + " ".join(
            f"{s} {sum(v) / len(v):.0%}" for s, v in rows[-1]["success"].items()), flush=True)
    best = choose(rows, cfg.rollouts * len(scenes) * len(seeds))
    record = {"env": suite.name, "split": "validation", "method": "pdp", "setting": "fit_optimizer", "seeds": seeds,
              "scenes": [str(s) for s in scenes], "rollouts": cfg.rollouts, "sampler": list(sampler),
              "gradient_norms_at_encoder_latent": {"seed": seeds[0], "draws": args.grad_draws, "norms": norms},
              "candidates": rows, "chosen": rows[best]["candidate"],
              "rule": "the first candidate (Adam, the current fit) is kept unless the best beats it by more than one "
                      "binomial standard error"}
    write_text_atomic(args.out, json.dumps(record, indent=1))
    print(f"chosen: {record['chosen']} -> {args.out}")
    return 0


def gradient_norms(policy, demo: Path, adapt: dict, draws: int) -> list[float]:
    """|grad L_fit| of ``policy`` at the encoder's latent of ``demo``, one per fitting batch drawn as the fit
    draws them, with the adaptation's objective (the sampled chunks with ``objective="sample"``)."""
    import torch

    from lerobot_pdp.adaptation import initial_latent
    from lerobot_pdp.benchmark.data import demo_episode
    from lerobot_pdp.latent_fitting import _stratified_batch, fit_loss, frozen_denoiser

    cfg, model = policy.config, policy.model
    objective = adapt.get("objective", cfg.fit_objective)
    with torch.inference_mode(False), torch.enable_grad():
        d = policy._demonstration(demo_episode(demo), "auto", need_action=True)
        windows = policy._demo_windows(d)
        z0 = initial_latent(model, cfg, d, "encoder", 0).float()
        frozen = frozen_denoiser(model.denoiser, model.noise_schedule)
        obs = frozen.observations(windows.obs_cond)
        out = []
        for draw in range(draws):
            g = torch.Generator().manual_seed(draw)
            idx = _stratified_batch(windows.segment, windows.n_segments, cfg.fit_batch_size, g)
            z = z0.clone().requires_grad_(True)
            loss = fit_loss(frozen, model.noise_schedule, windows, z, idx, cfg.fit_noise_samples, cfg.fit_lambda, g,
                            obs, sample_steps=cfg.num_inference_steps if objective == "sample" else None)
            out.append(round(float(torch.autograd.grad(loss, z)[0].norm()), 4))
    return out


if __name__ == "__main__":
    raise SystemExit(main())
