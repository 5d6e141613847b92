"""Results of a benchmark run: per-seed evaluations aggregated into ``results.json``, runs of different seeds
merged into one, and the markdown table in the paper's layout."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from .machine import cpu_model
from .settings import (
    FROZEN,
    INIT_STEPS,
    VALIDATION_RECORDS,
    BenchmarkConfig,
    TrainSettings,
    budget_key,
    film_form,
    scene_label,
)


def validation_summary(record: str | None) -> dict[str, Any] | None:
    """What the committed validation record ``record`` (repository-relative) chose, per method, on which
    seeds, scenes and rollouts; None without a record or outside a source checkout (no ``docs/``)."""
    path = Path(__file__).resolve().parents[2] / record if record else None
    if path is None or not path.is_file():
        return None
    rec = json.loads(path.read_text())
    return {name: {"seeds": m["seeds"], "scenes": m["scenes"], "rollouts": rec["rollouts"], "chosen": m["chosen"]}
            for name, m in rec["methods"].items()}


def _agg(values: list[float]) -> dict[str, Any]:
    v = [x for x in values if x is not None]
    return {"values": v, "mean": float(np.mean(v)) if v else None, "std": float(np.std(v)) if v else None}


def frozen_record(env: str, cfg: BenchmarkConfig) -> dict[str, Any]:
    """What is frozen for a run of ``cfg`` besides "train" (``settings.FROZEN``) and a summary of the validation
    record it came from. Taken when the run starts: the record may be replaced while a long run goes on."""
    budget = budget_key(cfg.quick, cfg.obs)
    record = VALIDATION_RECORDS.get((env, budget))
    return {"methods": FROZEN.get((env, budget), {}), "validation_record": record,
            "validation": validation_summary(record)}


def applied_train(settings: TrainSettings, steps: int) -> dict[str, Any]:
    """The shared training budget as the runs' ``lerobot-train`` got it: ``steps``, and the warm-up
    :func:`lerobot_pdp.benchmark.training.train_args` caps at a tenth of them."""
    return {**asdict(settings), "steps": steps, "warmup_steps": min(settings.warmup_steps, steps // 10)}


def aggregate(env: str, cfg: BenchmarkConfig, per_run: dict[str, dict[int, dict]], init_abl: dict[int, dict],
              settings: TrainSettings, steps: int, frozen: dict[str, Any] | None = None) -> dict[str, Any]:
    """``results.json`` layout: methods -> scene<k> (``scene_val<k>`` for validation scenes) -> success [per seed],
    mean, std (+ collision, modes); ``split`` and ``scenes`` say which split was evaluated. ``frozen``: the
    run's :func:`frozen_record` as taken at its start (default: taken now)."""
    out: dict[str, Any] = {"env": env, "split": cfg.split, "scenes": list(cfg.scenes), "seeds": cfg.seeds,
                           "rollouts": cfg.rollouts, "quick": cfg.quick,
                           "train": applied_train(settings, steps), "film": film_form(env, cfg.film),
                           "rec_reduction": cfg.rec_reduction,
                           "device": cfg.device, "cpu": cpu_model(),
                           "frozen": frozen if frozen is not None else frozen_record(env, cfg),
                           "methods": {}}
    observation = cfg.observation()
    if observation is not None:
        out["observation"] = observation
    for name, runs in per_run.items():
        entry: dict[str, Any] = {"seeds": [s for s in cfg.seeds if s in runs]}
        for scene in cfg.scenes:
            rows = [runs[s]["scenes"][str(scene)] for s in cfg.seeds if s in runs]
            d: dict[str, Any] = {"success": [r["success"] for r in rows]}
            a = _agg(d["success"])
            d.update(mean=a["mean"], std=a["std"], collision=_agg([r["collision"] for r in rows])["mean"])
            for k in ("coverage", "entropy", "steer_accuracy"):
                if rows and k in rows[0]:
                    d[k] = _agg([r.get(k) for r in rows])["mean"]
            entry[scene_label(scene)] = d
        shifted = [entry[scene_label(s)]["mean"] for s in cfg.scenes
                   if s != 0 and entry[scene_label(s)]["mean"] is not None]
        entry["shifted_avg"] = float(np.mean(shifted)) if shifted else None
        steps_used = sorted({r["inference_steps"] for r in runs.values() if r.get("inference_steps") is not None})
        if steps_used:
            entry["inference_steps"] = steps_used
            entry["timestep_spacing"] = sorted({r.get("timestep_spacing", "unrecorded") for r in runs.values()})
        # where each evaluation ran (cached evaluations are reused on any device; caches from before the
        # key existed say "unrecorded"): CPU and CUDA rollouts share seeds but not bit-identical arithmetic
        entry["eval_devices"] = sorted({r.get("device", "unrecorded") for r in runs.values()})
        adapt_used = [r["adapt"] for r in runs.values() if r.get("adapt")]
        if adapt_used:
            entry["adapt"] = adapt_used[0] if all(a == adapt_used[0] for a in adapt_used) else adapt_used
        out["methods"][name] = entry
    if init_abl:
        keys = [k for k in next(iter(init_abl.values())) if k != "per_scene"]
        out["init_ablation"] = {k: _agg([init_abl[s][k] for s in init_abl]) for k in keys}
        for k in keys:  # per shifted scene, mean over the seeds (caches from before per_scene have none)
            scenes = [a["per_scene"][k] for a in init_abl.values() if k in a.get("per_scene", {})]
            if scenes:
                out["init_ablation"][k]["scenes"] = {sc: _agg([r[sc] for r in scenes])["mean"] for sc in scenes[0]}
    return out


# Per-scene keys that are means over seeds (each seed ran the same number of rollouts), so a merge can
# weight them by seed count and stay exact.
_SEED_MEANS = ("collision", "coverage", "entropy", "steer_accuracy")


_PER_METHOD_FROZEN = ("methods", "validation")  # frozen-record parts keyed by method


def _merged_frozen(results: list[tuple[str, dict[str, Any]]]) -> dict[str, Any] | None:
    """The frozen record of merged runs: what each method ran with must be one setting in every file.

    A method's settings are compared wherever they are recorded, or where the method ran without a record;
    a file that neither ran a method nor records it says nothing about it (a run frozen before another
    method was validated still merges with that method's later runs). The other parts (which validation
    record) must be equal. Per-method parts are joined."""
    first_name, first = results[0]
    if all(res.get("frozen") == first.get("frozen") for _, res in results):
        return first.get("frozen")
    records = [(name, res.get("frozen") or {}, res) for name, res in results]
    for name, fr, _ in records[1:]:
        for key in {*fr, *records[0][1]} - set(_PER_METHOD_FROZEN):
            if fr.get(key) != records[0][1].get(key):
                raise ValueError(f"{name}: frozen {key} is {fr.get(key)!r} but {first_name} has "
                                 f"{records[0][1].get(key)!r}; only runs of the same protocol can be merged")
    out: dict[str, Any] = {k: v for k, v in records[0][1].items() if k not in _PER_METHOD_FROZEN}
    methods = sorted({m for _, fr, res in records for m in [*res["methods"], *(m for part in _PER_METHOD_FROZEN
                                                                                 for m in fr.get(part) or {})]})
    for method in methods:
        seen: list[tuple[str, tuple]] = []
        for name, fr, res in records:
            setting = tuple((fr.get(part) or {}).get(method) for part in _PER_METHOD_FROZEN)
            if method in res["methods"] or any(v is not None for v in setting):
                seen.append((name, setting))
        for name, setting in seen[1:]:
            if setting != seen[0][1]:
                mine, theirs = (dict(zip(_PER_METHOD_FROZEN, v, strict=True)) for v in (setting, seen[0][1]))
                raise ValueError(f"{name}: frozen is {mine!r} for {method} but {seen[0][0]} has {theirs!r}; only "
                                 "runs of the same protocol can be merged")
        for part, value in zip(_PER_METHOD_FROZEN, seen[0][1], strict=True):
            if value is not None:
                out.setdefault(part, {})[method] = value
    return out


def merge_results(results: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """One ``results.json`` from several runs of the same protocol that hold different seeds (e.g. seeds run
    on other machines or days). ``results`` is ``[(name, results_dict), ...]``; names go into errors.

    Refused, naming the files and the key: other env, rollouts, training settings, frozen settings,
    observations or scenes, and a (method, seed) present twice. Per-seed success lists are concatenated in seed order, mean / std
    recomputed; the other per-scene figures are seed-weighted means of the runs' means."""
    if len(results) < 2:
        raise ValueError(f"merging needs at least two results files, got {len(results)}")
    for name, res in results:
        missing = [k for k in ("env", "rollouts", "seeds", "train", "methods") if not isinstance(res, dict) or k not in res]
        if missing:
            raise ValueError(f"{name}: not a benchmark results.json (no {', '.join(missing)})")
    first_name, first = results[0]
    for name, res in results[1:]:
        if res.get("split", "test") != first.get("split", "test"):  # files from before splits: test
            raise ValueError(f"{name}: split is {res.get('split', 'test')!r} but {first_name} has "
                             f"{first.get('split', 'test')!r}; validation and test runs are never merged")
        for key in ("env", "rollouts", "quick", "train", "observation"):
            mine, theirs = res.get(key), first.get(key)
            if mine != theirs:
                if isinstance(mine, dict) and isinstance(theirs, dict):  # name the fields that differ, not both dicts
                    differ = sorted(k for k in {*mine, *theirs} if mine.get(k) != theirs.get(k))
                    mine, theirs = ({k: d.get(k) for k in differ} for d in (mine, theirs))
                raise ValueError(f"{name}: {key} is {mine!r} but {first_name} has {theirs!r}; "
                                 "only runs of the same protocol can be merged")
        if None not in (res.get("film"), first.get("film")) and res["film"] != first["film"]:  # older: unrecorded
            raise ValueError(f"{name}: PDP's FiLM form is {res['film']!r} but {first_name} has {first['film']!r}; "
                             "only runs of the same protocol can be merged")
        if res.get("rec_reduction", "mean") != first.get("rec_reduction", "mean"):  # older files: the mean
            raise ValueError(f"{name}: PDP's L_rec reduction is {res.get('rec_reduction', 'mean')!r} but {first_name} "
                             f"has {first.get('rec_reduction', 'mean')!r}; only runs of the same protocol can be merged")
    frozen = _merged_frozen(results)
    # method -> [(seed, source name, entry)] with each seed's index into the entry's per-seed lists
    rows: dict[str, list[tuple[int, str, dict[str, Any], int]]] = {}
    for name, res in results:
        for method, entry in res["methods"].items():
            seeds = entry.get("seeds", res["seeds"])  # files from before per-method seeds: all seeds ran
            short = [k for k in entry if k.startswith("scene") and len(entry[k]["success"]) != len(seeds)]
            if short:  # an older file's method that missed some seeds: which ones is not recorded
                raise ValueError(f"{name}: {method} {short[0]} has {len(entry[short[0]]['success'])} per-seed "
                                 f"values for seeds {seeds}; cannot tell which seeds they are")
            for i, seed in enumerate(seeds):
                clash = [n for s, n, _, _ in rows.get(method, []) if s == seed]
                if clash:
                    raise ValueError(f"{method} seed {seed} is in both {clash[0]} and {name}; "
                                     "merge runs of different seeds only")
                rows.setdefault(method, []).append((seed, name, entry, i))
    out: dict[str, Any] = {key: first[key] for key in ("env", "rollouts", "quick", "train")}
    for key in ("split", "observation"):  # equal in every file (checked above)
        if key in first:
            out[key] = first[key]
    if frozen is not None:
        out["frozen"] = frozen
    films = {res["film"] for _, res in results if res.get("film")}
    if films:
        out["film"] = films.pop()
    out["rec_reduction"] = first.get("rec_reduction", "mean")
    if all(res.get("scenes") == first.get("scenes") for _, res in results) and "scenes" in first:
        out["scenes"] = first["scenes"]
    out["device"] = "/".join(sorted({str(res.get("device", "unrecorded")) for _, res in results}))
    out["cpu"] = "/".join(sorted({str(res.get("cpu", "unrecorded")) for _, res in results}))
    out["seeds"] = sorted({s for r in rows.values() for s, *_ in r})
    out["merged_from"] = [name for name, _ in results]
    out["methods"] = {}
    first_method, first_rows = next(iter(rows.items()))
    table_scenes = [k for k in first_rows[0][2] if k.startswith("scene")]  # one table: every method, every scene
    for method, per_seed in rows.items():
        per_seed.sort(key=lambda r: r[0])
        scenes = [k for k in per_seed[0][2] if k.startswith("scene")]
        for _, name, entry, _ in per_seed:
            got = [k for k in entry if k.startswith("scene")]
            if got != table_scenes:
                raise ValueError(f"{name}: {method} has scenes {got} but {first_rows[0][1]}'s {first_method} has "
                                 f"{table_scenes}; merge runs of the same scenes")
        merged: dict[str, Any] = {"seeds": [r[0] for r in per_seed]}
        for scene in scenes:
            success = [entry[scene]["success"][i] for _, _, entry, i in per_seed]
            a = _agg(success)
            d: dict[str, Any] = {"success": success, "mean": a["mean"], "std": a["std"]}
            for key in _SEED_MEANS:
                if key in per_seed[0][2][scene]:
                    d[key] = _agg([entry[scene].get(key) for _, _, entry, _ in per_seed])["mean"]
            merged[scene] = d
        shifted = [merged[s]["mean"] for s in scenes if s != "scene0" and merged[s]["mean"] is not None]
        merged["shifted_avg"] = float(np.mean(shifted)) if shifted else None
        steps_used = sorted({s for _, _, e, _ in per_seed for s in e.get("inference_steps", [])})
        if steps_used:
            merged["inference_steps"] = steps_used
            merged["timestep_spacing"] = sorted({s for _, _, e, _ in per_seed for s in e.get("timestep_spacing", [])})
        merged["eval_devices"] = sorted({d for _, _, e, _ in per_seed for d in e.get("eval_devices", ["unrecorded"])})
        adapt_used = []  # each run's adaptation settings besides the defaults, once each
        for _, _, e, _ in per_seed:
            for a in (e["adapt"] if isinstance(e.get("adapt"), list) else [e["adapt"]] if e.get("adapt") else []):
                if a not in adapt_used:
                    adapt_used.append(a)
        if adapt_used:
            merged["adapt"] = adapt_used[0] if len(adapt_used) == 1 else adapt_used
        out["methods"][method] = merged
    taught = [(name, res["teach"]) for name, res in results if "teach" in res]
    if taught:  # runs with --teach: one record of every (method, seed) they taught
        from .teaching import merge_teach_records

        out["teach"] = merge_teach_records(taught)
    abl = [res["init_ablation"] for _, res in results if "init_ablation" in res]
    if abl:
        keys = abl[0].keys()
        out["init_ablation"] = {k: _agg([v for a in abl for v in a.get(k, {}).get("values", [])]) for k in keys}
        for k in keys:  # per-scene means, weighted by each file's seed count; only if every file has them
            parts = [(a[k]["scenes"], len(a[k]["values"])) for a in abl if a.get(k, {}).get("scenes")]
            if parts and len(parts) == len(abl):
                n = sum(w for _, w in parts)
                out["init_ablation"][k]["scenes"] = {sc: sum(r[sc] * w for r, w in parts) / n for sc in parts[0][0]}
    return out


def _fmt(d: dict[str, Any] | None) -> str:
    if not d or d.get("mean") is None:
        return "–"
    if len(d.get("success", d.get("values", []))) > 1:  # several seeds: mean ± std
        return f"{100 * d['mean']:.1f} ± {100 * d['std']:.1f}"
    return f"{100 * d['mean']:.1f}"


def results_markdown(res: dict[str, Any]) -> str:
    """The paper's table layout: rows = methods, columns = original scene and constraint shifts."""
    scenes = [k for k in next(iter(res["methods"].values())) if k.startswith("scene")]
    shifts = [s[5:] for s in scenes if s != "scene0" and not s.startswith("scene_")]
    # the average is over the shifted scenes run: said when a run left some of the test scenes 1-3 out
    avg = "Shifted avg" if not shifts or shifts == ["1", "2", "3"] else f"Shifted avg (shift {', '.join(shifts)})"
    head = ["Method", *[("Original (scene 0)" if s == "scene0" else f"Validation {s[6:]}" if s.startswith("scene_")
                         else f"Shift {s[5:]}") for s in scenes], avg, "Scene-0 coverage"]
    split = " (validation split)" if res.get("split") == "validation" else ""
    lines = [f"### {res['env']}{split} — success rate (%), {res['rollouts']} rollouts per scene, seeds {res['seeds']}",
             "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, entry in res["methods"].items():
        cov = entry.get("scene0", {}).get("coverage")
        label = name if entry.get("seeds", res["seeds"]) == res["seeds"] else f"{name} (seeds {entry['seeds']})"
        row = [label, *[_fmt(entry[s]) for s in scenes],
               "–" if entry.get("shifted_avg") is None else f"{100 * entry['shifted_avg']:.1f}",
               "–" if cov is None else f"{100 * cov:.0f}"]
        lines.append("| " + " | ".join(row) + " |")
    if "init_ablation" in res:
        lines += ["", "#### Latent initialisation (PDP, mean success over shifted scenes, %)", "",
                  "| init | " + " | ".join(f"{s} steps" for s in INIT_STEPS) + " |", "|---|" + "---|" * len(INIT_STEPS)]
        for init in ("encoder", "random"):
            cells = [_fmt(res["init_ablation"].get(f"{init}@{s}")) for s in INIT_STEPS]
            lines.append(f"| {'warm (encoder)' if init == 'encoder' else 'random'} | " + " | ".join(cells) + " |")
        per_scene = {k: v["scenes"] for k, v in res["init_ablation"].items() if v.get("scenes")}
        if per_scene:
            shifts = list(next(iter(per_scene.values())))
            lines += ["", "| init @ fitting steps | " + " | ".join(f"Shift {sc}" for sc in shifts) + " |",
                      "|---|" + "---|" * len(shifts)]
            for k, rates in per_scene.items():
                label = k.replace("encoder", "warm (encoder)").replace("@", " @ ")
                lines.append(f"| {label} | " + " | ".join(f"{100 * rates[sc]:.1f}" for sc in shifts) + " |")
    t = res["train"]
    if res.get("merged_from"):
        lines += ["", f"Merged from: {', '.join(res['merged_from'])}."]
    if res.get("observation"):
        o = res["observation"]
        lines += ["", f"Observations: state, environment state and camera '{o['camera']}' "
                  f"({o['image_size']}x{o['image_size']}) for every method."]
    lines += ["", f"Training: {t['steps']} steps, batch {t['batch_size']}, lr {t['lr']}, "
              f"{t['episodes_per_mode']} demos/mode (same for every method)."]
    if res.get("film"):
        lines.append(f"PDP's FiLM form: {res['film']}.")
    if res.get("rec_reduction", "mean") != "mean":
        lines.append(f"PDP's L_rec: the {res['rec_reduction']} of each trace's squared error.")
    sampler = [f"{name} {'/'.join(map(str, e['inference_steps']))}"
               + (f" ({'/'.join(e['timestep_spacing'])})" if e.get("timestep_spacing") else "")
               for name, e in res["methods"].items() if e.get("inference_steps")]
    if sampler:
        lines.append(f"DDIM sampler steps (grid): {', '.join(sampler)}.")
    devices = {name: "/".join(e["eval_devices"]) for name, e in res["methods"].items() if e.get("eval_devices")}
    if devices:
        same = len(set(devices.values())) == 1
        lines.append("Evaluated on: " + (f"{next(iter(devices.values()))} (every method)." if same
                                         else ", ".join(f"{n} {d}" for n, d in devices.items()) + "."))
    if res.get("cpu"):  # results from before the key say nothing
        lines.append(f"CPU: {res['cpu']}.")
    adapted = [f"{name} {e['adapt']}" for name, e in res["methods"].items() if e.get("adapt")]
    if adapted:
        lines.append(f"Adaptation settings besides the defaults: {'; '.join(adapted)}.")
    return "\n".join(lines) + "\n"
