"""Why do pick-place rollouts fail? Classify each one by what happened at the grasp and at the release.

Rolls out a trained PDP checkpoint (the benchmark's ``runs/pdp/seed<k>``) in one scene with the latent the
benchmark fitted there (its ``eval.json``; in scene 0, rollout i with mode i's mean latents and the seed the
protocol gives that mode, i.e. the benchmark's own scene-0 rollouts while n <= 40), logging every executed
action, and prints per rollout where the gripper first closed (distance end effector - object, speed) and the outcome: success, collision,
"never grasped" (closed outside the 3 cm grasp radius), "released off target" or "never released"; for
grasped rollouts also where the carry ended (object - target distance when the gripper opened again, or how
far along y the object got while still held).

    python scripts/diagnostics/pick_place_grasps.py runs/pick_place_full3/runs/pdp/seed0 --scene 1 -n 20
    python scripts/diagnostics/pick_place_grasps.py runs/pick_place_full3/runs/pdp/seed0 --scene 0 -n 40
"""

from __future__ import annotations

import argparse
import json
import os
from collections import Counter
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs import pick_place as pp
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory holding pretrained_model/ and eval.json")
    ap.add_argument("--scene", type=int, default=1, choices=(0, 1, 2, 3))
    ap.add_argument("-n", type=int, default=20, help="rollouts (seeds 5, 6, ...; scene 0: one per mode)")
    ap.add_argument("--n-action-steps", type=int, help="execute this many actions per chunk (default: the checkpoint's)")
    ap.add_argument("--seed", type=int, default=0, help="scene 0: the benchmark seed the run was evaluated with")
    args = ap.parse_args()

    log: list[tuple[np.ndarray, np.ndarray, np.ndarray, bool]] = []
    step = pp.PickPlaceEnv.step

    def logged_step(self, action):  # record what the env executed, then step as usual
        out = step(self, action)
        log.append((self.ee_pos.copy(), self.object_pos.copy(), np.asarray(action, float).copy(), self.grasped))
        return out

    pp.PickPlaceEnv.step = logged_step
    policy, pre, post = load_run(args.run)
    if args.n_action_steps is not None:
        most = policy.config.horizon - policy.config.n_obs_steps + 1
        if not 1 <= args.n_action_steps <= most:
            ap.error(f"--n-action-steps must be in 1..{most} (horizon - n_obs_steps + 1), got {args.n_action_steps}")
        policy.config.n_action_steps = args.n_action_steps
        policy.reset()  # the action queue's length comes from the config
    if args.scene:
        fitted = json.loads((args.run / "eval.json").read_text())["scenes"][str(args.scene)]["z"]
        policy.set_latent(torch.tensor(fitted, dtype=torch.float32))
    else:
        means = policy.mode_latents()
    suite = get_suite_env("pick-place")
    tally: Counter[str] = Counter()
    for i in range(args.n):
        log.clear()
        if args.scene:
            r = run_rollouts(suite, args.scene, policy, pre, post, 1, 5 + i, batch_size=1).results[0]
        else:  # as evaluate_scene0 seeds mode m's rollouts
            m = sorted(means)[i % len(means)]
            policy.set_latent(means[m])
            r = run_rollouts(suite, 0, policy, pre, post, 1, args.seed * 10_000 + 97 * m, batch_size=1).results[0]
        ee, obj, act = (np.array([row[k] for row in log]) for k in range(3))
        closes = [t for t in range(1, len(act)) if act[t, 3] > 0 >= act[t - 1, 3]][:3]
        held = [t for t in range(len(log)) if log[t][3]]
        released = [t for t in range(held[0], len(act)) if act[t, 3] <= 0] if held else []
        kind = ("success" if r.success else "collision" if r.collided
                else "released off target" if released else "never released" if held else "never grasped")
        tally[kind] += 1
        print(f"{i:2d}{f' mode {m:2d}' if not args.scene else ''} {kind:20s} first closes at steps {closes}: ee-object "
              f"{[round(float(np.linalg.norm(ee[t] - obj[t])), 3) for t in closes]} m, speed "
              f"{[round(float(np.linalg.norm(ee[t] - ee[t - 1])), 4) for t in closes]} m/step", flush=True)
        if not held:  # a carry without the object: how far the end effector went
            print(f"   never held the object: end effector's max y {ee[:, 1].max():.2f} (target y {pp.TARGET[1]:.2f})")
        else:  # the carry's end: where the gripper opened again, or how far the object got without it
            end = released[0] if released else len(obj) - 1
            print(f"   {'opens' if released else 'still closed'} at step {end}: object-target "
                  f"{np.linalg.norm(obj[end] - pp.TARGET):.3f} m, speed {np.linalg.norm(ee[end] - ee[end - 1]):.4f} "
                  f"m/step; object's max y {obj[held[0]:, 1].max():.2f} (target y {pp.TARGET[1]:.2f})", flush=True)
    print(f"scene {args.scene}: {dict(tally)}")


if __name__ == "__main__":
    main()
