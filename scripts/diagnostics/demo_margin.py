"""Is a shifted scene lost because its demonstration passes too close to an obstacle? Re-record it with margin.

A scene that ships way-points (a new route) gets its demonstration from the scripted expert along them. This
re-records that demonstration along shifted way-points (``--shift dx,dy,dz``, metres, added to every
way-point; the barriers stay), reports each demonstration's minimum clearance to the barriers, and, unless
``--no-fit``, fits the run's PDP to it exactly as the benchmark adapts (encoder warm start, the checkpoint's
fitting settings, the run's seed) and rolls out in the unchanged scene (the protocol's rollout seeds). The
zero shift reproduces the benchmark's own demonstration (same recording seed). One JSON line per shift:

    python scripts/diagnostics/demo_margin.py runs/kitchen_val/runs/pdp/seed100 --env kitchen-microwave \\
        --scene val3 --shift=0,0,0 --shift=-0.03,0,0 --rollouts 20   # "=" lets a value start with "-"
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def _shift(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"--shift takes dx,dy,dz in metres (e.g. 0,-0.03,0), got {text!r}")
    return values


def main() -> None:
    from run_args import add_run_args, eval_record

    import lerobot_pdp.envs.recording as recording
    from lerobot_pdp.benchmark.data import demo_episode
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import scene_seed_offset
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.scene import load_scene, shipped_scene_path
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_run_args(ap)  # a scene that ships way-points
    ap.add_argument("--shift", type=_shift, action="append", required=True, help="dx,dy,dz added to every way-point")
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--no-fit", action="store_true", help="only record the demonstrations and report their clearance")
    args = ap.parse_args()
    if args.rollouts < 1:
        ap.error(f"--rollouts must be >= 1, got {args.rollouts}")

    suite = get_suite_env(args.env)
    if load_scene(args.scene, suite.scene_key).waypoints is None:
        ap.error(f"{args.env} scene {args.scene} ships no way-points: its demonstration is a training mode's")
    base = json.loads(shipped_scene_path(suite.scene_key, args.scene).read_text())

    if not args.no_fit:
        seed = eval_record(ap, args.run, "its seed is read from there")["seed"]
        policy, pre, post = load_run(args.run)
        policy.eval()
    with tempfile.TemporaryDirectory() as tmp:
        for i, shift in enumerate(args.shift):
            scene = copy.deepcopy(base)
            scene["waypoints"] = [[round(a + d, 4) for a, d in zip(w, shift, strict=True)] for w in base["waypoints"]]
            scene_file = Path(tmp) / f"scene_{i}.json"
            scene_file.write_text(json.dumps(scene))
            root = Path(tmp) / f"demo_{i}"
            try:  # the benchmark's recording seed for this scene (data.ensure_demo)
                recording.make_dataset(suite.name, root, scene=str(scene_file), episodes_per_mode=1,
                                       seed=1000 * scene_seed_offset(args.scene), progress=False, waypoints="scene")
            except recording.DemoGenerationError as e:
                print(json.dumps({"shift": shift, "error": str(e)}), flush=True)
                continue
            clearance = recording.read_dataset_meta(root)["episode_min_clearance"][0]  # None: no barrier
            row = {"shift": shift, "waypoints": scene["waypoints"],
                   "demo_min_clearance": None if clearance is None else round(clearance, 4)}
            if not args.no_fit:
                res = policy.fit_latent(demo_episode(root), init="encoder", seed=seed)
                batch = run_rollouts(suite, args.scene, policy, pre, post, args.rollouts,
                                     seed * 10_000 + scene_seed_offset(args.scene))
                policy.set_latent(None)
                row |= {"z_init": [round(v, 3) for v in res.z_init.tolist()], "z": [round(v, 3) for v in res.z.tolist()],
                        "success": batch.success_rate, "collision": batch.collision_rate}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
