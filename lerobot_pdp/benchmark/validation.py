"""Choosing inference-time settings on the validation split, with the same budget for every method.

Two stages, each a fixed list of candidates evaluated on the trained validation runs (scene 0 and the env's
validation scenes, validation seeds); nothing here ever touches a test scene or test seed:

1. **Sampler** (PDP and DP, one shared list, each method choosing its own): DDIM steps and grid. Both
   sample with diffusers' DDIM as LeRobot's ``diffusion`` steps it, so a candidate is the same sampler for
   both. Scored on every scene of the split (scene 0 included: the sampler acts there too).
2. **Adaptation** (every method, as many candidates each): the steps and step size of PDP's latent fit,
   DP's noise optimisation and BC's fine-tuning, each evaluated with that method's chosen sampler. Scored
   on the validation scenes only (scene 0 adapts nothing).

A candidate's score is its mean success over those scenes and the seeds. The default (the method's current
setting: ``settings.FROZEN``, else the env's sampler and the adaptation's defaults; listed first) is kept
unless the best candidate beats it by more than one binomial standard error of the default's score over the
rollouts behind it: a setting changes on evidence, not on one rollout. ``validate`` writes
``out/validation.json`` (every candidate's per-scene, per-seed success and each method's choice), which
``settings.FROZEN`` then freezes for the test run, by hand so that the change is reviewed.

When a candidate list changes, ``reuse`` (``--reuse-validation``) evaluates only the new candidates: the rows
of an earlier ``validation.json`` stand for a retrained run once its own evaluation reproduces the earlier
record's rollouts exactly (same checkpoint, same seeded rollouts), else every candidate is evaluated anew.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import write_text_atomic
from .evaluation import cached_evaluation, evaluate_method, sampler_of
from .settings import CAMERAS, IMAGE_SIZE, BenchmarkConfig, Method, frozen_for, methods_for, split_scenes

# (DDIM steps, grid). At K = 20 steps the grids coincide, so 20 appears once.
SAMPLER_CANDIDATES: tuple[tuple[int, str], ...] = (
    (20, "leading"), (10, "leading"), (10, "trailing"), (5, "leading"), (5, "trailing"),
)

# Per adaptation, six candidates each (the default first): steps x step size around each default
# (PDP fit 100 x 0.05 with |z|^2 weight 1e-3, DP noise 100 x 0.05, BC fine-tuning 100 x 1e-5); PDP also tries
# fitting the chunks it samples instead of its noise predictions (what DP's noise adaptation scores), DP one
# noise per executed chunk instead of one for the whole rollout, and PDP that same noise per chunk on top of
# its fitted z (``fit_latent(noise="chunks")``). The last took the place of PDP's 10-step fit, which no
# validation run had chosen (nor its 300-step one), so that every method keeps six candidates.
ADAPT_CANDIDATES: dict[str, tuple[dict[str, Any], ...]] = {
    "fit_latent": ({}, {"steps": 0}, {"noise": "chunks"}, {"steps": 300}, {"lam": 0.0}, {"objective": "sample"}),
    "noise": ({}, {"steps": 30}, {"steps": 300}, {"lr": 0.01}, {"lr": 0.2}, {"per_chunk": True}),
    "finetune": ({}, {"lr": 1e-4}, {"lr": 1e-3}, {"steps": 300, "lr": 1e-4}, {"steps": 300, "lr": 1e-3},
                 {"steps": 30, "lr": 1e-3}),
}


def candidate_tag(sampler: tuple[int, str] | None, adapt: dict[str, Any]) -> str:
    """File-name tag of one candidate, e.g. ``s20-leading`` or ``s20-leading_lr0.2_steps300``."""
    tag = f"s{sampler[0]}-{sampler[1]}" if sampler else "nosampler"
    return tag + "".join(f"_{k}{v}" for k, v in sorted(adapt.items()))


def _score(evals: list[dict[str, Any]], scenes: list[int | str]) -> float:
    return float(np.mean([e["scenes"][str(s)]["success"] for e in evals for s in scenes]))


def choose(rows: list[dict[str, Any]], rollouts: int) -> int:
    """Index of the chosen candidate: the best score if it beats the default (row 0) by more than one
    standard error of the default's score (``rollouts`` = rollouts behind each score), else the default."""
    best = max(range(len(rows)), key=lambda i: (rows[i]["score"], -i))
    p = rows[0]["score"]
    se = float(np.sqrt(max(p * (1 - p), 1e-12) / max(rollouts, 1)))
    return best if rows[best]["score"] - p > se else 0


def check_reuse(name: str, runs: dict[int, Path], previous: dict[str, Any], source: str,
                scenes: list[int | str]) -> dict[str, Any]:
    """May the rows of ``previous`` (an earlier validation record of method ``name``, from file ``source``)
    stand for the runs ``{seed: run_dir}``? Only if their checkpoints are the ones it validated: each run's
    own evaluation (``eval.json``, made by the protocol from the retrained checkpoint) must give exactly the
    success the earlier record holds for that candidate on every scene both evaluated. Returns what was
    compared; raises, naming the seed, scene and both values, where it differs."""
    seeds, want = sorted(runs), [str(s) for s in scenes]
    if previous["seeds"] != seeds or previous["scenes"] != want:
        raise ValueError(f"{source}: {name} was validated on seeds {previous['seeds']}, scenes {previous['scenes']}; "
                         f"this run has seeds {seeds}, scenes {want}: rows are reused for the same ones only")
    rows = previous["sampler"] + previous["adapt"]
    compared: list[dict[str, Any]] = []
    for i, seed in enumerate(seeds):
        own_file = runs[seed] / "eval.json"
        own = json.loads(own_file.read_text())
        sampler = (own["inference_steps"], own["timestep_spacing"]) if own.get("inference_steps") else None
        tag = candidate_tag(sampler, own.get("adapt", {}))
        for row in (r for r in rows if r["tag"] == tag):
            for scene, rates in row["success"].items():
                if scene not in own["scenes"]:
                    continue
                now = own["scenes"][scene]["success"]
                if rates[i] != now:
                    raise ValueError(f"{own_file}: {name} seed {seed} scene {scene} ({tag}) succeeds {now:.3f}, the "
                                     f"run {source} validated {rates[i]:.3f}: not the same checkpoint")
                compared.append({"seed": seed, "candidate": tag, "scene": scene, "success": now})
    if not compared:
        raise ValueError(f"{source}: no candidate of {name} matches its runs' own evaluations; nothing shows the "
                         "checkpoints are the ones it validated")
    return {"source": source, "compared": compared}


def _evaluate(suite, method: Method, runs: dict[int, Path], demos, cfg: BenchmarkConfig,
              sampler: tuple[int, str] | None, adapt: dict[str, Any], scenes: list[int | str]) -> list[dict[str, Any]]:
    from dataclasses import replace

    sub = replace(cfg, scenes=tuple(scenes), inference_steps=sampler[0] if sampler else None,
                  timestep_spacing=sampler[1] if sampler else None)
    tag = candidate_tag(sampler, adapt)
    out = []
    for seed, run in runs.items():
        ckpt = run / "pretrained_model"
        made = cached_evaluation(run / "eval.json", sampler_of(ckpt, sub), ckpt, adapt)
        own = made and made.get("rollouts") == sub.rollouts and set(map(str, scenes)) <= set(made["scenes"])
        # the protocol's own evaluation, when it is this candidate; else one cache file per candidate
        cache = run / "eval.json" if own else run / "validation" / f"eval_{tag}.json"
        out.append(evaluate_method(suite, method, ckpt, demos, sub, seed, run, adapt_kwargs=adapt, cache=cache))
    return out


def _evaluate_in_worker(args: tuple) -> None:
    """One candidate in a worker process (its result lands in the candidate's cache file)."""
    import torch

    import lerobot_pdp.envs  # noqa: F401  (a spawned process registers the suite anew)

    *args, threads = args
    torch.set_num_threads(threads)
    _evaluate(*args)


def _prefetch(suite, method: Method, runs: dict[int, Path], demos, cfg: BenchmarkConfig,
              candidates: list[tuple[tuple[int, str] | None, dict[str, Any], list[int | str]]]) -> None:
    """Evaluate a stage's candidates in ``cfg.jobs`` processes side by side; the sequential pass that
    follows then reads every result from its cache. Nothing to do with one job."""
    if cfg.jobs <= 1 or len(candidates) <= 1:
        return
    import multiprocessing as mp
    import os
    from concurrent.futures import ProcessPoolExecutor

    jobs = min(cfg.jobs, len(candidates))
    threads = max(1, (os.cpu_count() or 1) // jobs)
    # spawn: the parent may hold CUDA or MuJoCo state that a forked child must not inherit
    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as pool:
        list(pool.map(_evaluate_in_worker,
                      [(suite, method, runs, demos, cfg, s, a, sc, threads) for s, a, sc in candidates]))


def validate_method(suite, method: Method, runs: dict[int, Path], demos, cfg: BenchmarkConfig,
                    previous: dict[str, Any] | None = None, source: str = "") -> dict[str, Any]:
    """Both stages for one method over its trained validation runs ``{seed: run_dir}``. ``previous``: the
    method's record in an earlier validation.json (file ``source``) whose candidates are reused, not
    evaluated again, once :func:`check_reuse` has shown the checkpoints are the same."""
    scenes = list(cfg.scenes)
    shifted = [s for s in scenes if s != 0]
    has_sampler = method.policy_type in ("pdp", "diffusion")
    record: dict[str, Any] = {"seeds": sorted(runs), "scenes": [str(s) for s in scenes], "sampler": [],
                              "adapt": []}
    old_rows: dict[tuple[str, str], dict[str, Any]] = {}
    if previous is not None:
        try:
            record["reuse_check"] = check_reuse(method.name, runs, previous, source, scenes)
            old_rows = {(stage, r["tag"]): r for stage in ("sampler", "adapt") for r in previous[stage]}
        except ValueError as e:  # another checkpoint: its rows say nothing about this one, so every candidate runs
            record["reuse_refused"] = str(e)
            print(f"[validate] {method.name}: nothing reused, every candidate is evaluated ({e})", flush=True)

    def reused(stage, sampler, adapt):
        r = old_rows.get((stage, candidate_tag(sampler, adapt)))
        return {**r, "reused": True} if r else None

    def row(sampler, adapt, evals, scored):
        return {"tag": candidate_tag(sampler, adapt), "sampler": list(sampler) if sampler else None,
                "adapt": adapt, "score": _score(evals, scored),
                "devices": sorted({e.get("device", "unrecorded") for e in evals}),
                "success": {str(s): [e["scenes"][str(s)]["success"] for e in evals] for s in scenes
                            if all(str(s) in e["scenes"] for e in evals)}}

    best_sampler: tuple[int, str] | None = None
    if has_sampler:
        rows = []
        # the method's current sampler (frozen, else the env's) is the default candidate
        current = tuple(frozen_for(suite.name, cfg.quick, method.name, cfg.obs).get("sampler")
                        or (cfg.inference_steps, cfg.timestep_spacing))
        samplers = [current, *[c for c in SAMPLER_CANDIDATES if c != current]]
        _prefetch(suite, method, runs, demos, cfg,
                  [(c, {}, scenes) for c in samplers if not reused("sampler", c, {})])
        for sampler in samplers:
            old = reused("sampler", sampler, {})
            rows.append(old or row(sampler, {}, _evaluate(suite, method, runs, demos, cfg, sampler, {}, scenes),
                                   scenes))
            print(f"[validate] {method.name} sampler {sampler}: {rows[-1]['score']:.1%}"
                  + (" (reused)" if old else ""), flush=True)
        record["sampler"] = rows
        best_sampler = samplers[choose(rows, cfg.rollouts * len(scenes) * len(runs))]
    rows = []
    current = frozen_for(suite.name, cfg.quick, method.name, cfg.obs).get("adapt", {})  # likewise
    adapts = [current, *[a for a in ADAPT_CANDIDATES[method.adapt] if a != current]]
    _prefetch(suite, method, runs, demos, cfg,
              [(best_sampler, a, shifted if a else scenes) for a in adapts if not reused("adapt", best_sampler, a)])
    for adapt in adapts:
        old = reused("adapt", best_sampler, adapt)
        rows.append(old or row(best_sampler, adapt, _evaluate(suite, method, runs, demos, cfg, best_sampler, adapt,
                                                              shifted if adapt else scenes), shifted))
        print(f"[validate] {method.name} adapt {adapt or 'default'}: {rows[-1]['score']:.1%}"
              + (" (reused)" if old else ""), flush=True)
    record["adapt"] = rows
    best = choose(rows, cfg.rollouts * len(shifted) * len(runs))
    record["chosen"] = {"sampler": list(best_sampler) if best_sampler else None, "adapt": rows[best]["adapt"]}
    return record


def load_reuse_record(cfg: BenchmarkConfig, env: str) -> dict[str, Any]:
    """The earlier validation record ``cfg.reuse_validation`` names, checked before anything trains: it must be
    a validation.json of ``env`` (the suite's name) with this run's rollouts per scene and observations
    (:meth:`BenchmarkConfig.observation`, camera resolved), else a ValueError naming the file. Taking the whole
    config keeps the run's start-up check and :func:`validate` from comparing different fields."""
    path = Path(cfg.reuse_validation)
    if not path.is_file():
        raise ValueError(f"--reuse-validation {path}: no such file (give an earlier validation.json)")
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"--reuse-validation {path} is not JSON ({e})") from e
    if not isinstance(record, dict) or not isinstance(record.get("methods"), dict):
        raise ValueError(f"--reuse-validation {path} is not a validation record (no 'methods')")
    for key, want in (("env", env), ("split", "validation"), ("rollouts", cfg.rollouts),
                      ("observation", cfg.observation())):
        if record.get(key) != want:
            raise ValueError(f"--reuse-validation {path}: {key} is {record.get(key)!r}, this run's is {want!r}; only a "
                             "record of the same env, split, rollouts and observations can be reused")
    return record


def _same_candidates(method: Method, previous: dict[str, Any]) -> bool:
    """Were ``method``'s candidates in the earlier record ``previous`` the ones listed now?"""
    same_adapt = previous.get("adapt_candidates", {}).get(method.adapt) == list(ADAPT_CANDIDATES[method.adapt])
    has_sampler = method.policy_type in ("pdp", "diffusion")
    return same_adapt and (not has_sampler or previous.get("sampler_candidates") == [list(c) for c in SAMPLER_CANDIDATES])


def validate(cfg: BenchmarkConfig, suite, methods: dict[str, Method], runs: dict[str, dict[int, Path]],
             demos) -> dict[str, Any]:
    """Both stages for every method; writes and returns ``cfg.out/validation.json``.

    With ``cfg.reuse_validation`` (an earlier validation.json of the same env and rollouts), each method run
    here reuses that record's rows if :func:`check_reuse` passes (else evaluates them all anew, recording
    why under ``reuse_refused``) and evaluates only the candidates it lacks; the
    methods of that record not run here are carried over as they are if their candidate lists are unchanged
    (else left out, with a note)."""
    if cfg.split != "validation":
        raise ValueError("settings are chosen on the validation split only (--split validation)")
    expected = set(map(str, split_scenes(suite.name, "validation")))
    if set(map(str, cfg.scenes)) != expected:
        raise ValueError(f"validation uses all of {sorted(expected)}, got {sorted(map(str, cfg.scenes))}")
    source = str(cfg.reuse_validation) if cfg.reuse_validation else ""
    previous = load_reuse_record(cfg, suite.name) if cfg.reuse_validation else {"methods": {}}
    out: dict[str, Any] = {"env": suite.name, "split": "validation", "rollouts": cfg.rollouts,
                           "sampler_candidates": [list(c) for c in SAMPLER_CANDIDATES],
                           "adapt_candidates": {k: list(v) for k, v in ADAPT_CANDIDATES.items()}, "methods": {}}
    observation = cfg.observation()
    if observation is not None:  # as in results.json: absent means the state variant
        out["observation"] = observation
    if source:
        out["reused_from"] = source
    for name in runs:
        out["methods"][name] = validate_method(suite, methods[name], runs[name], demos, cfg,
                                               previous["methods"].get(name), source)
    for name, rec in previous["methods"].items():
        if name in runs:
            continue
        if name in methods and _same_candidates(methods[name], previous):
            out["methods"][name] = rec
        else:
            print(f"[validate] {name} of {source} left out: its candidate list has changed since", flush=True)
    write_text_atomic(Path(cfg.out) / "validation.json", json.dumps(out, indent=1))
    return out


def choose_training_setting(method: str, setting: str, candidates: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Choose a training setting (e.g. PDP's FiLM form) among validation runs that each trained ``method``
    with one candidate (``candidates``: name -> that run's ``results.json``, the current setting first).

    A candidate's score is the method's mean success over every scene of the split, scene 0 included (a
    training setting acts there too), and the seeds, each evaluated with the protocol's default sampler and
    adaptation; :func:`choose`'s rule picks (the default stays unless beaten by more than one standard error).
    """
    rows: list[dict[str, Any]] = []
    first: tuple | None = None
    for name, res in candidates.items():
        if res.get("split") != "validation":
            raise ValueError(f"{name}: a {res.get('split', 'test')!r} run; training settings are chosen on the "
                             "validation split only")
        entry = res["methods"].get(method)
        if entry is None:
            raise ValueError(f"{name}: no {method} in its results (methods: {sorted(res['methods'])})")
        keys = sorted(k for k in entry if k.startswith("scene"))
        this = (res["env"], keys, entry["seeds"], res["rollouts"])
        if first is None:
            first = this
        elif this != first:
            raise ValueError(f"{name}: env / scenes / seeds / rollouts {this} differ from the first candidate's "
                             f"{first}; compare like with like")
        success = {k: entry[k]["success"] for k in keys}
        score = float(np.mean([v for vals in success.values() for v in vals]))
        rows.append({"candidate": name, "score": score, "success": success, "film": res.get("film"),
                     "rec_reduction": res.get("rec_reduction", "mean"),
                     "train": res["train"]})
    if first is None:
        raise ValueError("no candidates")
    env, scenes, seeds, rollouts = first
    best = choose(rows, rollouts * len(scenes) * len(seeds))
    return {"env": env, "split": "validation", "method": method, "setting": setting, "seeds": seeds,
            "scenes": scenes, "rollouts": rollouts, "candidates": rows, "chosen": rows[best]["candidate"],
            "rule": "the first candidate (current setting) is kept unless the best beats it by more than one "
                    "binomial standard error"}


def _record_methods(env: str) -> dict[str, Method]:
    """Every method a validation record of ``env`` may hold (state and camera variants): its adaptation and
    policy type name the candidate lists it was validated with (its adaptation's; the sampler list if it
    samples by diffusion)."""
    import lerobot_pdp.envs  # noqa: F401  (registers the suite envs)

    from ..envs.suite import get_suite_env

    suite = get_suite_env(env)
    known = dict(methods_for(suite))
    if suite.name in CAMERAS:
        known = {**methods_for(suite.with_camera(CAMERAS[suite.name], IMAGE_SIZE)), **known}
    return known


def merge_validation_records(records: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """One ``validation.json`` from validation runs of the same protocol that validated different methods
    (one output folder per method). Refused, naming the file and the key: another env, split, rollout count or
    observation variant (state / camera), a method present twice, and a candidate list that differs between
    two records holding methods validated with it (e.g. DP's noise candidates in two records that both hold
    DP-like methods). Lists only the other methods use may differ: the merged record keeps each list from the
    records whose methods used it."""
    if not records:
        raise ValueError("no validation records to merge")
    first_name, first = records[0]
    for name, rec in records[1:]:
        for key in ("env", "split", "rollouts", "observation"):
            if rec.get(key) != first.get(key):
                raise ValueError(f"{name}: {key} is {rec.get(key)!r} but {first_name} has {first.get(key)!r}; "
                                 "only validation runs of the same protocol can be merged")
    known = _record_methods(first["env"])
    merged = {**first, "adapt_candidates": dict(first.get("adapt_candidates", {})), "methods": {}}
    used: dict[tuple[str, str], tuple[str, Any]] = {}  # (key, adaptation) -> (record, list) of a method's record
    for name, rec in records:
        for method_name, method_rec in rec["methods"].items():
            if method_name in merged["methods"]:
                raise ValueError(f"{name}: {method_name!r} already validated in another input")
            method = known.get(method_name)
            if method is None:
                raise ValueError(f"{name}: {method_name!r} is not a benchmark method of {first['env']} "
                                 f"(known: {sorted(known)})")
            lists = [("adapt_candidates", method.adapt, rec.get("adapt_candidates", {}).get(method.adapt))]
            if method.policy_type in ("pdp", "diffusion"):
                lists.append(("sampler_candidates", "", rec.get("sampler_candidates")))
            for key, kind, value in lists:
                label = f"{key}[{kind!r}]" if kind else key
                seen = used.setdefault((key, kind), (name, value))
                if seen[1] != value:
                    raise ValueError(f"{name}: {label} (validated for {method_name}) is {value!r} but {seen[0]} "
                                     f"has {seen[1]!r}; only methods validated with the same candidates can be merged")
                if kind:
                    merged["adapt_candidates"][kind] = value
                else:
                    merged["sampler_candidates"] = value
            merged["methods"][method_name] = method_rec
    return merged


def validation_markdown(res: dict[str, Any]) -> str:
    """The candidates and choices of ``validation.json`` as tables (success %, mean over seeds)."""
    lines = [f"# Validation: {res['env']} ({res['rollouts']} rollouts per scene)", ""]
    for name, rec in res["methods"].items():
        lines += [f"## {name} (seeds {', '.join(map(str, rec['seeds']))})", "",
                  "| stage | candidate | " + " | ".join(f"scene {s}" for s in rec["scenes"]) + " | score |",
                  "|---|---|" + "---|" * len(rec["scenes"]) + "---|"]
        for stage in ("sampler", "adapt"):
            for r in rec[stage]:
                cells = [f"{100 * np.mean(r['success'][s]):.1f}" if s in r["success"] else "" for s in rec["scenes"]]
                dev = "" if r.get("devices", ["cpu"]) == ["cpu"] else f" ({'/'.join(r['devices'])})"
                mark = " †" if r.get("reused") else ""
                lines.append(f"| {stage} | {r['tag']}{dev}{mark} | " + " | ".join(cells) + f" | {100 * r['score']:.1f} |")
        lines += ["", f"Chosen: sampler {rec['chosen']['sampler']}, adaptation {rec['chosen']['adapt'] or 'default'}.",
                  ""]
        if "reuse_refused" in rec:
            lines += [f"Nothing reused: {rec['reuse_refused']}.", ""]
        if "reuse_check" in rec:
            n = len(rec["reuse_check"]["compared"])
            lines += [f"† reused from {rec['reuse_check']['source']}: the retrained checkpoint reproduced that record's "
                      f"success exactly on the {n} (seed, candidate, scene) evaluations both hold.", ""]
    return "\n".join(lines)
