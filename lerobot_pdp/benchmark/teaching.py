"""Teaching a new route on the scenes no latent reaches: PDP's ``teach`` beside BC and DP fine-tuned with the same
rehearsal, one demonstration, the same step budget.

For each method and setting: the taught policy's success on the new route (PDP steered to its new mode; BC and DP
as they act, they have nothing to select with) and what it kept of scene 0 (PDP: each old mode steered by its
latent, success and the share that took the mode it was given; BC and DP: success and the modes their sampled
rollouts cover), beside the untaught checkpoint's scene 0 under the same rollout seeds, and the wall time of the
teaching. Rollouts and teaching are seeded per (seed, scene).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from ..atomic import write_text_atomic
from ..envs.suite import SuiteEnv
from ..episodes import read_episodes
from .data import demo_episode
from .evaluation import evaluate_scene0, summarize_rollouts
from .rollouts import run_rollouts
from .settings import TEACH_FROZEN, BenchmarkConfig, Method, budget_key, scene_seed_offset, teach_scenes
from .training import load_policy

# The settings compared on the validation scenes, the same grid for every method (the same tuning budget):
# fine-tuning steps and Adam step size, from a short gentle run to 3000 steps, and 1000 at the training lr (1e-3);
# every batch 64 windows, a quarter of them from the demonstration. Measured in rounds on avoiding val4: the
# first three, then 3000 steps when 300 -> 1000 had helped every method.
TEACH_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"steps": 300, "lr": 1e-4}, {"steps": 1000, "lr": 1e-4}, {"steps": 1000, "lr": 1e-3}, {"steps": 3000, "lr": 1e-4},
)
# And one candidate of each method's own, the same count for all: PDP's new latent had landed half a spread from
# a training latent, so the latent geometry places it instead; BC and DP take 3000 steps at the training lr.
TEACH_EXTRA: dict[str, tuple[dict[str, Any], ...]] = {
    "pdp": ({"steps": 1000, "lr": 1e-4, "latent": "geometry"},),
    "dp": ({"steps": 3000, "lr": 1e-3},),
    "bc": ({"steps": 3000, "lr": 1e-3},),
}
TEACH_BATCH = 64
TEACH_SHARE = 0.25
TAUGHT_METHODS = ("pdp", "dp", "bc")  # PDP teaches a mode; BC and DP are fine-tuned with the same rehearsal


def _rehearsal_episodes(data: Path) -> list[dict]:
    eps = read_episodes(data, ["observation.state", "observation.environment_state", "action"])
    return [{k: v for k, v in item.items() if k.startswith(("observation.", "action"))} for item in eps.values()]


def teach_policy(method: Method, policy, pre, demo_root: Path, data: Path, seed: int, steps: int, lr: float,
                 rehearsal: list[dict] | None = None, latent: str = "encoder") -> tuple[Any, dict[str, Any]]:
    """The taught policy and what teaching reported: PDP's ``teach`` (its new mode made active), or the
    baseline fine-tuned on the demonstration with rehearsal of ``data``."""
    from .baselines import finetune_with_rehearsal

    t0 = time.perf_counter()
    if method.policy_type == "pdp":
        res = policy.teach((demo_root, 0), data, steps=steps, lr=lr, demo_share=TEACH_SHARE, seed=seed, latent=latent)
        policy.set_latent(policy.mode_latents()[res.mode])
        info = {"mode": res.mode, "z": res.z.tolist(), "nearest_spreads": res.nearest_spreads}
        return policy, {**info, "teach_seconds": time.perf_counter() - t0}
    episodes = rehearsal if rehearsal is not None else _rehearsal_episodes(data)
    tuned = finetune_with_rehearsal(policy, pre, demo_episode(demo_root), episodes, steps, lr, TEACH_BATCH,
                                    TEACH_SHARE, seed)
    return tuned, {"teach_seconds": time.perf_counter() - t0}


def scene0_kept(suite: SuiteEnv, method: Method, policy, pre, post, n: int, seed: int,
                modes: list[int] | None = None) -> dict[str, Any]:
    """Scene 0 of ``policy``: PDP steered to each of ``modes`` (default all), the others sampled."""
    batch = evaluate_scene0(suite, method, policy, pre, post, n, seed, modes=modes)
    return summarize_rollouts(batch, suite.n_modes, with_modes=True)


def evaluate_teaching(suite: SuiteEnv, method: Method, ckpt: Path, data: Path, demos: dict[str | int, Path],
                      seed: int, out: Path, rollouts: int = 40, rollouts_scene0: int | None = None,
                      candidates: tuple[dict[str, Any], ...] = TEACH_CANDIDATES,
                      sampler: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every candidate setting on every scene of ``demos`` for one trained (method, seed); cached in ``out``
    (a JSON file written after each evaluation, so a run cut short goes on from there). ``sampler``: keyword
    arguments of ``load_policy`` (the method's frozen DDIM steps and grid, the device), as its evaluation uses."""
    sampler = sampler or {}
    result: dict[str, Any] = json.loads(out.read_text()) if out.is_file() else {}
    result.update(method=method.name, seed=seed, rollouts=rollouts)
    rollouts_scene0 = rollouts_scene0 or rollouts
    base = result.setdefault("base_scene0", {})
    if not base:
        policy, pre, post = load_policy(ckpt, **sampler)
        base.update(scene0_kept(suite, method, policy, pre, post, rollouts_scene0, seed * 10_000))
        write_text_atomic(out, json.dumps(result, indent=1))
    rehearsal = None if method.policy_type == "pdp" else _rehearsal_episodes(data)
    runs = result.setdefault("runs", {})
    keys = []
    for cand in candidates:
        for scene, demo_root in demos.items():
            key = f"{scene} steps={cand['steps']} lr={cand['lr']:g}" + (f" latent={cand['latent']}" if "latent" in cand
                                                                         else "")
            keys.append(key)
            if key in runs:
                continue
            policy, pre, post = load_policy(ckpt, **sampler)
            old_modes = sorted(policy.mode_latents()) if method.steerable else None
            offset = scene_seed_offset(scene)
            actor, info = teach_policy(method, policy, pre, demo_root, data, seed * 10_000 + offset, cand["steps"],
                                       cand["lr"], rehearsal, cand.get("latent", "encoder"))
            new = run_rollouts(suite, scene, actor, pre, post, rollouts, seed * 10_000 + offset, label=f"scene {scene}")
            kept = scene0_kept(suite, method, actor, pre, post, rollouts_scene0, seed * 10_000, modes=old_modes)
            runs[key] = {"scene": str(scene), **cand, "new_route": summarize_rollouts(new, suite.n_modes, False),
                         "scene0": kept, **info}
            print(f"[teach] {method.name} seed {seed} {key}: new route {runs[key]['new_route']['success']:.0%}, "
                  f"scene 0 {kept['success']:.0%} (base {base['success']:.0%}), {info['teach_seconds']:.0f} s")
            write_text_atomic(out, json.dumps(result, indent=1))
    result["chosen"], result["chosen_keeps_scene0"] = choose_teaching({k: runs[k] for k in keys}, base)
    write_text_atomic(out, json.dumps(result, indent=1))
    return result


RETENTION_POINTS = 5.0  # scene-0 success may drop by at most this many points for a setting to be chosen


def choose_teaching(runs: dict[str, dict[str, Any]], base: dict[str, Any]) -> tuple[str, bool]:
    """The chosen setting (a run key without its scene) and whether it keeps scene 0: the best new-route success
    (mean over the scenes of a setting) among the settings whose scene 0 stays within ``RETENTION_POINTS`` of the
    untaught checkpoint's on every scene, or among all settings when none does; ties go to the one listed first."""
    settings: dict[str, list[dict[str, Any]]] = {}
    for key, run in runs.items():
        settings.setdefault(key.split(" ", 1)[1], []).append(run)
    kept = {s: all(100 * (r["scene0"]["success"] - base["success"]) >= -RETENTION_POINTS for r in rows)
            for s, rows in settings.items()}
    pool = [s for s in settings if kept[s]] or list(settings)
    best = max(pool, key=lambda s: (sum(r["new_route"]["success"] for r in settings[s]) / len(settings[s]),
                                    -list(settings).index(s)))
    return best, kept[best]


def teach_candidates(env: str, cfg: BenchmarkConfig, method: str) -> tuple[dict[str, Any], ...]:
    """Every candidate on the validation split; the frozen one (``settings.TEACH_FROZEN``) on the test split."""
    if cfg.split == "validation":
        return TEACH_CANDIDATES + TEACH_EXTRA.get(method, ())
    chosen = TEACH_FROZEN.get((env, budget_key(cfg.quick, cfg.obs)), {}).get(method)
    if chosen is None:
        raise ValueError(f"--teach on the test split: no teaching setting of {method} on {env} is frozen yet "
                         "(settings.TEACH_FROZEN): choose it with --split validation --teach first")
    return (chosen,)


def run_teaching(suite: SuiteEnv, cfg: BenchmarkConfig, methods: dict[str, Method], ckpts: dict[tuple[str, int], Path],
                 data: Path, demos: dict[int | str, Path], out: Path,
                 method_cfgs: dict[str, BenchmarkConfig] | None = None) -> dict[str, Any]:
    """``benchmark --teach``: :func:`evaluate_teaching` for every (method, seed) that can be taught (PDP, DP, BC),
    on the split's zero-mode scenes; writes ``teach.json`` and ``teach.md`` in ``out``."""
    scenes = teach_scenes(suite.name, cfg.split, cfg.scenes)
    n0 = -(-cfg.rollouts // suite.n_modes) * suite.n_modes  # every old mode the same number of rollouts
    record: dict[str, Any] = {"env": suite.name, "split": cfg.split, "rollouts": cfg.rollouts, "rollouts_scene0": n0,
                              "batch_size": TEACH_BATCH, "demo_share": TEACH_SHARE, "runs": {}}
    for name, method in methods.items():
        if name not in TAUGHT_METHODS:
            continue
        for seed in cfg.seeds:
            mcfg = (method_cfgs or {}).get(name, cfg)  # the method's frozen sampler, as its evaluation samples
            sampler = {"inference_steps": mcfg.inference_steps, "timestep_spacing": mcfg.timestep_spacing,
                       "device": mcfg.device}
            res = evaluate_teaching(suite, method, ckpts[(name, seed)], data, {s: demos[s] for s in scenes}, seed,
                                    out / "runs" / name / f"seed{seed}" / "teach.json", cfg.rollouts, n0,
                                    teach_candidates(suite.name, cfg, name), sampler)
            record["runs"].setdefault(name, {})[str(seed)] = res
    write_text_atomic(out / "teach.json", json.dumps(record, indent=1))
    write_text_atomic(out / "teach.md", teach_markdown(record))
    return record


def merge_teach_records(records: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """One ``--teach`` record from runs of the same protocol that taught different (method, seed)s, e.g. BC and DP
    run as two benchmarks side by side. ``records`` is ``[(name, record), ...]``; names go into errors."""
    first_name, first = records[0]
    protocol = [k for k in first if k != "runs"]
    runs: dict[str, dict[str, Any]] = {}
    for name, rec in records:
        for key in sorted(set(protocol) | set(rec) - {"runs"}):  # a key either record lacks differs too
            if rec.get(key) != first.get(key):
                raise ValueError(f"{name}: teaching {key} is {rec.get(key)!r} but {first_name} has "
                                 f"{first.get(key)!r}; only runs of the same protocol can be merged")
        for method, seeds in rec["runs"].items():
            for seed, res in seeds.items():
                if seed in runs.get(method, {}):
                    raise ValueError(f"{method} seed {seed} is taught in two of the merged runs ({name} is one)")
                runs.setdefault(method, {})[seed] = res
    return {**{k: first[k] for k in protocol}, "runs": runs}


def teach_markdown(record: dict[str, Any]) -> str:
    """One row per (method, seed, scene, setting): new-route success, scene 0 kept against the untaught checkpoint."""
    lines = [f"# Teaching a new route: {record['env']}, {record['split']} split",
             "",
             f"{record['rollouts']} rollouts on the new route, {record['rollouts_scene0']} on scene 0; batches of "
             f"{record['batch_size']} windows, {record['demo_share']:.0%} from the demonstration.",
             "",
             "| method | seed | scene | steps | lr | latent | new route | scene 0 (untaught) | scene-0 steer accuracy | "
             "scene-0 modes covered | teach s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, seeds in record["runs"].items():
        for seed, res in seeds.items():
            base = res["base_scene0"]
            for run in res["runs"].values():
                kept = run["scene0"]
                acc = kept.get("steer_accuracy")
                lines.append(
                    f"| {name} | {seed} | {run['scene']} | {run['steps']} | {run['lr']:g} | "
                    f"{run.get('latent', 'encoder') if name == 'pdp' else '-'} | "
                    f"{run['new_route']['success']:.1%} | {kept['success']:.1%} ({base['success']:.1%}) | "
                    f"{'-' if acc is None else f'{acc:.1%}'} | {kept['coverage']:.0%} | "
                    f"{run['teach_seconds']:.0f} |")
    lines.append("")
    for name, seeds in record["runs"].items():
        for seed, res in seeds.items():
            if record["split"] == "test":  # one setting, frozen before: nothing is chosen here
                lines.append(f"Taught {name} (seed {seed}) with its frozen setting {res.get('chosen')} "
                             "(settings.TEACH_FROZEN, chosen on the validation split).")
                continue
            kept = "" if res.get("chosen_keeps_scene0") else "; no setting keeps scene 0, so among all"
            lines.append(f"Chosen for {name} (seed {seed}): {res.get('chosen')} (the best new route among the settings "
                         f"whose scene 0 drops by at most {RETENTION_POINTS:g} points{kept}).")
    return "\n".join(lines) + "\n"
