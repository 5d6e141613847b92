"""Training a taught checkpoint further with lerobot-train: does the taught mode survive?

``lerobot-train --policy.path=TAUGHT`` rehearses a taught checkpoint's modes in every batch, from the demonstrations
it keeps (``lerobot_pdp/taught_rehearsal.py``). This measures what that buys on the validation split: PDP trained
with the benchmark's settings (validation seed), taught the route of one zero-mode scene (``--scene``) with the
benchmark's frozen setting (as ``scripts/teach_again.py`` does, and reusing its stages in ``--out``), then trained
``--steps`` more steps by ``lerobot-train`` with the benchmark's training flags on the same dataset, twice: with
the rehearsal (the default share) and with ``--policy.taught_rehearsal_share=0`` (the taught mode dropped, the
earlier behaviour); the latter is also taught again with ``teach --taught-from`` (the earlier way back). For each
checkpoint: the scene steered to the taught mode (to the latent it was taught at where the mode was dropped), and
scene 0 steered to each training mode, with the benchmark's rollout seeds. ``--new-data N``: also trained further,
rehearsed, on a new scene-0 recording of N episodes per mode (another seed): another dataset whose mode labels leave
the taught id free, where the taught mode joins its behaviours. Nothing is chosen from it.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/train_taught_further.py --env avoiding --out runs/teach_again

Every stage is kept in ``--out``: a run cut short goes on from there. Writes ``train_taught_further.json`` and
``train_taught_further.md`` there.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

from teach_again import _evaluate, _teach

from lerobot_pdp.atomic import write_text_atomic
from lerobot_pdp.benchmark.data import ensure_dataset, ensure_demo
from lerobot_pdp.benchmark.settings import (
    SETTINGS,
    TEACH_FROZEN,
    VALIDATION_SEED_MIN,
    methods_for,
    scene_seed_offset,
    teach_scenes,
)
from lerobot_pdp.benchmark.teaching import TEACH_SHARE
from lerobot_pdp.benchmark.training import load_policy, run_logged, train_args, train_method
from lerobot_pdp.envs import get_suite_env
from lerobot_pdp.taught import teach_again_from


def _train_further(taught: Path, out: Path, method, data: Path, seed: int, settings, steps: int,
                   *extra: str) -> tuple[Path, float | None]:
    """``lerobot-train --policy.path=taught`` with the benchmark's flags for ``steps`` steps into ``out`` (reused when
    its last checkpoint is there); the checkpoint and the training's wall time (None when reused)."""
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    if (ckpt / "model.safetensors").is_file():
        return ckpt, None
    args = [f"--policy.path={taught}" if a == "--policy.type=pdp" else a
            for a in train_args(method, data, seed, settings, steps)]
    args += [f"--output_dir={out}", *extra]
    if out.exists():  # a training cut short: lerobot-train refuses an existing output folder
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    # as the benchmark trains: its loader workers, trainer threads and column views, the log beside the run
    run_logged(args, out.with_name(out.name + ".log"), steps, f"train further ({out.name})")
    return ckpt, time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="avoiding")
    ap.add_argument("--seed", type=int, default=VALIDATION_SEED_MIN, help="training seed, a validation one")
    ap.add_argument("--scene", default="val4", help="zero-mode validation scene whose route is taught")
    ap.add_argument("--steps", type=int, default=2000, help="lerobot-train steps after teaching")
    ap.add_argument("--rollouts", type=int, default=40, help="rollouts in the taught scene per checkpoint")
    ap.add_argument("--new-data", type=int, default=0, metavar="N",
                    help="also train further on a new scene-0 recording of N episodes per mode (0: not)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.seed < VALIDATION_SEED_MIN:
        raise SystemExit(f"--seed {args.seed} is a test seed: this measurement runs on validation seeds "
                         f"(>= {VALIDATION_SEED_MIN})")
    suite = get_suite_env(args.env)
    if args.scene not in teach_scenes(suite.name, "validation"):
        raise SystemExit(f"{args.scene} is not a zero-mode validation scene of {suite.name}")
    settings = SETTINGS[suite.name][0]
    method = methods_for(suite)["pdp"]
    setting = TEACH_FROZEN[(suite.name, "full")]["pdp"]
    out = args.out
    data = ensure_dataset(suite, out, settings)
    base = train_method(method, data, out / "runs" / "pdp" / f"seed{args.seed}", args.seed, settings, settings.steps)
    demo = ensure_demo(suite, out, args.scene)[0]
    seed = args.seed * 10_000
    name = f"route-{args.scene}"
    taught = _teach(base, out / "taught" / "first", demo, data, setting, seed + scene_seed_offset(args.scene), name)
    further = out / "train_further"
    seconds = {}
    rehearsed, seconds["rehearsed"] = _train_further(taught, further / "rehearsed", method, data, args.seed, settings,
                                                     args.steps)
    dropped, seconds["not rehearsed"] = _train_further(taught, further / "not_rehearsed", method, data, args.seed,
                                                       settings, args.steps, "--policy.taught_rehearsal_share=0")
    again = further / "not_rehearsed_taught_again"
    if not (again / "model.safetensors").is_file():
        t0 = time.perf_counter()
        teach_again_from(dropped, taught, again, data, steps=setting["steps"], lr=setting["lr"], demo_share=TEACH_SHARE,
                         seed=seed + scene_seed_offset(args.scene))
        seconds["taught again"] = time.perf_counter() - t0

    taught_policy = load_policy(taught)[0]
    mode = taught_policy.model.bank.taught_modes()[0]
    runs = [("taught", taught), ("trained further, rehearsed", rehearsed), ("trained further, not rehearsed", dropped),
            ("trained further, not rehearsed, taught again", again)]
    if args.new_data:
        from lerobot_pdp.envs.recording import make_dataset

        new = out / "data" / f"{suite.scene_key}_scene0_new{args.new_data}"
        if not (new / "meta" / "info.json").is_file():
            make_dataset(suite.name, new, scene=0, episodes_per_mode=args.new_data, seed=1, **suite.camera_kwargs)
        tag = f"trained further on new data ({args.new_data}/mode), rehearsed"
        ckpt, seconds[tag] = _train_further(taught, further / f"new_data_{args.new_data}_rehearsed", method, new,
                                            args.seed, settings, args.steps)
        runs.append((tag, ckpt))
    z_taught = taught_policy.mode_latents()[mode]
    n0 = -(-args.rollouts // suite.n_modes) * suite.n_modes
    evals = further / "evaluations"
    rows: dict[str, dict[str, Any]] = {}
    for tag, ckpt in runs:
        latents = load_policy(ckpt)[0].mode_latents()
        key = tag.replace(", ", "_").replace(" ", "_").replace("(", "").replace(")", "").replace("/", "_per_")
        rows[tag] = {"steered": "mode" if mode in latents else "the latent it was taught at (mode dropped)",
                     args.scene: _evaluate(evals / f"{key}_{args.scene}.json", ckpt, suite, args.scene,
                                           latents[mode] if mode in latents else z_taught, args.rollouts, seed),
                     "scene 0": _evaluate(evals / f"{key}_0.json", ckpt, suite, 0, None, n0, seed)}
    record = {"env": suite.name, "seed": args.seed, "scene": args.scene, "taught_mode": mode,
              "training_steps": settings.steps, "further_steps": args.steps, "teach": {**setting, "demo_share": TEACH_SHARE},
              "rollouts": args.rollouts, "rollouts_scene0": n0,
              "seconds": {k: round(v) for k, v in seconds.items() if v is not None}, "rows": rows}
    old = out / "train_taught_further.json"
    if old.is_file():  # a rerun from the cached stages keeps the times measured when they ran
        record["seconds"] = {**json.loads(old.read_text()).get("seconds", {}), **record["seconds"]}
    write_text_atomic(old, json.dumps(record, indent=1))
    lines = [f"| checkpoint | {args.scene} success (steered to) | scene 0 success |", "|---|---|---|"]
    for tag, res in rows.items():
        lines.append(f"| {tag} | {100 * res[args.scene]['success']:.1f} ({res['steered']}) | "
                     f"{100 * res['scene 0']['success']:.1f} |")
    write_text_atomic(out / "train_taught_further.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
