"""Teaching twice on a benchmark env: does the second teaching keep the route taught first?

A taught checkpoint keeps its demonstrations (``taught_demonstrations.safetensors``) so that teaching it again
rehearses the modes taught before at their latents. This measures what that buys on the validation split: PDP
trained with the benchmark's settings (validation seed), taught the route of one zero-mode scene (``--first``),
then taught the route of another (``--second``) twice from that checkpoint: with the first demonstration
rehearsed (what ``teach`` does) and without it (the checkpoint's taught demonstrations removed, as a checkpoint
taught before they were kept). Teaching uses the benchmark's frozen setting (``TEACH_FROZEN``) and seeds, and
rollouts the benchmark's seeds per scene. For each checkpoint: the first scene steered to the first taught mode,
the second scene steered to the second, and scene 0 steered to each training mode. Nothing is chosen from it.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/teach_again.py --env avoiding --out runs/teach_again

Every stage is kept in ``--out`` (dataset, training, taught checkpoints, one JSON per evaluation): a run cut short
goes on from there. Writes ``teach_again.json`` and ``teach_again.md`` there.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

from lerobot_pdp.atomic import write_text_atomic
from lerobot_pdp.benchmark.data import ensure_dataset, ensure_demo
from lerobot_pdp.benchmark.evaluation import summarize_rollouts
from lerobot_pdp.benchmark.rollouts import run_rollouts
from lerobot_pdp.benchmark.settings import (
    SETTINGS,
    TEACH_FROZEN,
    VALIDATION_SEED_MIN,
    methods_for,
    scene_seed_offset,
    teach_scenes,
)
from lerobot_pdp.benchmark.teaching import TEACH_SHARE, scene0_kept
from lerobot_pdp.benchmark.training import load_policy, train_method
from lerobot_pdp.envs import get_suite_env
from lerobot_pdp.taught import teach_checkpoint
from lerobot_pdp.taught_demos import TAUGHT_DEMOS


def _teach(parent: Path, out: Path, demo: Path, data: Path, setting: dict[str, Any], seed: int, name: str,
           rehearse_taught: bool = True) -> Path:
    """``lerobot-pdp teach``'s own path: ``parent`` taught ``demo``'s route as mode ``name`` into ``out`` (reused when
    there). ``rehearse_taught`` False: taught from a copy of ``parent`` without its taught demonstrations."""
    if (out / "model.safetensors").is_file():
        return out
    if not rehearse_taught:
        bare = out.with_name(out.name + ".base")
        shutil.rmtree(bare, ignore_errors=True)
        shutil.copytree(parent, bare, ignore=shutil.ignore_patterns(TAUGHT_DEMOS))
        parent = bare
    _, res = teach_checkpoint(parent, (demo, 0), out, data, steps=setting["steps"], lr=setting["lr"],
                              demo_share=TEACH_SHARE, seed=seed, name=name)
    print(f"[teach-again] {out.name}: mode {res.mode} ({name}) in {res.seconds:.0f} s")
    return out


def _evaluate(cache: Path, ckpt: Path, suite, scene: int | str, steer: Any, rollouts: int,
              seed: int) -> dict[str, Any]:
    """Rollouts of ``ckpt`` in ``scene`` steered to ``steer`` (a mode's name, or a latent), or scene 0's training
    modes each steered in turn (``steer`` None); cached in ``cache``."""
    if cache.is_file():
        return json.loads(cache.read_text())
    policy, pre, post = load_policy(ckpt)
    if steer is None:
        method = methods_for(suite)["pdp"]
        training = [m for m in sorted(policy.mode_latents()) if m not in policy.model.bank.taught_modes()]
        res = scene0_kept(suite, method, policy, pre, post, rollouts, seed, modes=training)
    else:
        policy.set_latent(policy.mode_latents()[steer] if isinstance(steer, str) else steer)
        batch = run_rollouts(suite, scene, policy, pre, post, rollouts, seed + scene_seed_offset(scene),
                             label=f"scene {scene}")
        res = summarize_rollouts(batch, suite.n_modes, False)
    cache.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(cache, json.dumps(res, indent=1))
    print(f"[evaluate] {cache.stem}: {res['success']:.1%} success", flush=True)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="avoiding")
    ap.add_argument("--seed", type=int, default=VALIDATION_SEED_MIN, help="training seed, a validation one")
    ap.add_argument("--first", default="val4", help="zero-mode validation scene taught first")
    ap.add_argument("--second", default="val5", help="zero-mode validation scene taught second")
    ap.add_argument("--rollouts", type=int, default=40, help="rollouts per scene and checkpoint")
    ap.add_argument("--steps", type=int, help="training steps (default: the env's benchmark budget; fewer for a try)")
    ap.add_argument("--teach-steps", type=int, help="teaching steps (default: the frozen setting; fewer for a try)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.seed < VALIDATION_SEED_MIN:
        raise SystemExit(f"--seed {args.seed} is a test seed: this measurement runs on validation seeds "
                         f"(>= {VALIDATION_SEED_MIN})")
    suite = get_suite_env(args.env)
    scenes = teach_scenes(suite.name, "validation")
    for scene in (args.first, args.second):
        if scene not in scenes:
            raise SystemExit(f"{scene} is not a zero-mode validation scene of {suite.name}: {list(scenes)}")
    settings = SETTINGS[suite.name][0]
    settings = dataclasses.replace(settings, steps=args.steps or settings.steps)
    setting = {**TEACH_FROZEN[(suite.name, "full")]["pdp"]}
    setting["steps"] = args.teach_steps or setting["steps"]
    out = args.out
    data = ensure_dataset(suite, out, settings)
    base = train_method(methods_for(suite)["pdp"], data, out / "runs" / "pdp" / f"seed{args.seed}", args.seed, settings,
                        settings.steps)
    demos = {s: ensure_demo(suite, out, s)[0] for s in (args.first, args.second)}
    first, second = (f"route-{s}" for s in (args.first, args.second))
    seed = args.seed * 10_000
    taught = out / "taught"
    t1 = _teach(base, taught / "first", demos[args.first], data, setting, seed + scene_seed_offset(args.first), first)
    t2 = {"rehearsed": _teach(t1, taught / "second_rehearsed", demos[args.second], data, setting,
                              seed + scene_seed_offset(args.second), second),
          "not rehearsed": _teach(t1, taught / "second_not_rehearsed", demos[args.second], data, setting,
                                  seed + scene_seed_offset(args.second), second, rehearse_taught=False)}
    evals = out / "evaluations"
    n0 = -(-args.rollouts // suite.n_modes) * suite.n_modes

    def ev(tag: str, ckpt: Path, scene: int | str, mode: str | None) -> dict[str, Any]:
        return _evaluate(evals / f"{tag}_{scene}.json", ckpt, suite, scene, mode, n0 if scene == 0 else args.rollouts,
                         seed)

    rows = {"trained": {"scene 0": ev("trained", base, 0, None)},
            "taught first": {args.first: ev("first", t1, args.first, first), "scene 0": ev("first", t1, 0, None)}}
    for tag, ckpt in t2.items():
        key = tag.replace(" ", "_")
        rows[f"taught second, first {tag}"] = {args.first: ev(key, ckpt, args.first, first),
                                               args.second: ev(key, ckpt, args.second, second),
                                               "scene 0": ev(key, ckpt, 0, None)}
    record = {"env": suite.name, "seed": args.seed, "training_steps": settings.steps, "first": args.first, "second": args.second,
              "teach": {**setting, "demo_share": TEACH_SHARE}, "rollouts": args.rollouts, "rollouts_scene0": n0,
              "rows": rows}
    write_text_atomic(out / "teach_again.json", json.dumps(record, indent=1))
    cols = [args.first, args.second, "scene 0"]
    lines = [f"| checkpoint | {' | '.join(f'{c} success' for c in cols)} |", "|---" * (len(cols) + 1) + "|"]
    for row, res in rows.items():
        cells = [f"{100 * res[c]['success']:.1f}" if c in res else "" for c in cols]
        lines.append(f"| {row} | {' | '.join(cells)} |")
    write_text_atomic(out / "teach_again.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
