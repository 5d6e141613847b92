"""Why do kitchen-microwave rollouts fail? Classify each one by what happened at the handle and during the pull.

Replays the benchmark's own rollouts of a trained checkpoint (a benchmark run directory ``runs/<method>/seed<k>``):
scene 0 with each mode's mean latent and the protocol's per-mode seeds and batches (steerable methods; others
sample), scenes 1-3 with the latent the benchmark fitted there (``eval.json``; PDP only). Every executed step is
logged, and each rollout is put in one class:

- ``success`` / ``collision`` (with a scene barrier; which barrier and which robot body);
- ``never at the handle``: the end effector never came within ``--reach`` of the handle;
- ``at the handle, door never moved``: it got there but the hinge never turned past -0.05 rad;
- ``lost the handle``: the door started opening, then the end effector left the handle (by more than
  ``--reach`` at the end) before the door passed the success angle;
- ``still pulling at the time limit``: holding the handle, door not open far enough.

For scenes 1-3 it first prints how close the scene's demonstration comes to a barrier (the margin a rollout
that imitates it has). For each rollout it also prints when the fingers first closed (the mean of the two finger commands below 0),
how far from the handle, the largest door opening and where the end effector ended.

    python scripts/diagnostics/kitchen_failures.py runs/kitchen_full/runs/pdp/seed0 --scene 0
    python scripts/diagnostics/kitchen_failures.py runs/kitchen_full/runs/dp/seed0 --scene 0
    python scripts/diagnostics/kitchen_failures.py runs/kitchen_full/runs/pdp/seed0 --scene 0 --episode-latents

``--episode-latents`` (PDP, scene 0): rollout i is conditioned on training demonstration i's own encoded latent
instead of its mode's mean, which tells a poor mode mean apart from a denoiser that fails with any latent.
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


def install_step_log():
    """Record, per env instance, every step of the first episode after each new rollout (as the benchmark's recorder)."""
    from lerobot_pdp.envs import kitchen_microwave as km

    step, reset = km.KitchenMicrowaveEnv.step, km.KitchenMicrowaveEnv.reset
    envs: list = []

    def logged_reset(self, *, seed=None, options=None):
        out = reset(self, seed=seed, options=options)
        if (options or {}).get("lerobot_new_rollout"):  # LeRobot's rollout; autoresets pass no options
            self.diag_log, self.diag_recording, self.diag_info = [], True, {}
            envs.append(self)
        elif not hasattr(self, "diag_recording"):
            self.diag_recording = False
        return out

    def logged_step(self, action):
        out = step(self, action)
        if self.diag_recording:
            obs, _, terminated, truncated, info = out
            a = np.asarray(action, float)
            self.diag_log.append((obs["agent_pos"][:3].copy(), obs["environment_state"][1:4].copy(),
                                  float(obs["environment_state"][0]), float(a[7:].mean())))
            if terminated or truncated:
                self.diag_recording, self.diag_info = False, dict(info)
                if info.get("collided"):
                    self.diag_info["hit"] = self.barrier_contacts()
        return out

    km.KitchenMicrowaveEnv.step, km.KitchenMicrowaveEnv.reset = logged_step, logged_reset
    return envs


def demo_clearance(out: Path, scene: int) -> None:
    """Print how close the scene's demonstration (the one PDP fitted) comes to the scene's barriers: the
    margin a rollout that imitates it has. Poses are set from the recorded joint positions, no stepping."""
    import mujoco

    from lerobot_pdp.benchmark.data import demo_episode, demo_root
    from lerobot_pdp.envs.kitchen_microwave import KitchenMicrowaveEnv
    from lerobot_pdp.envs.suite import get_suite_env

    states = demo_episode(demo_root(get_suite_env("kitchen-microwave"), out, scene))["observation.state"]
    env = KitchenMicrowaveEnv(scene=scene)
    env.reset(seed=0)
    clearance = []
    for s in states:  # agent_pos = end effector xyz, then the kitchen's robot qpos (9) and qvel (9)
        env.data.qpos[:9] = s[3:12]
        mujoco.mj_forward(env.model, env.data)
        clearance.append(env.clearance())
    t = int(np.argmin(clearance))
    print(f"scene-{scene} demonstration: {len(states)} steps, closest to a barrier {clearance[t]:.3f} m at step {t}")
    env.close()


def classify(log: list, info: dict, reach: float) -> tuple[str, str]:
    from lerobot_pdp.envs.kitchen_microwave import DOOR_OPEN

    ee, handle, door, fingers = (np.array([row[k] for row in log]) for k in range(4))
    dist = np.linalg.norm(ee - handle, axis=1)
    closes = [t for t in range(len(fingers)) if fingers[t] < 0 and (t == 0 or fingers[t - 1] >= 0)]
    opens_again = [t for t in range(1, len(fingers)) if fingers[t] >= 0 > fingers[t - 1]]
    if info.get("is_success"):
        kind = "success"
    elif info.get("collided"):
        kind = "collision"
        if info.get("hit"):
            kind += f" ({', '.join(info['hit'])})"
    elif dist.min() > reach:
        kind = "never at the handle"
    elif door.min() > -0.05:
        kind = "at the handle, door never moved"
    elif dist[-1] > reach:
        kind = "lost the handle"
    else:
        kind = "still pulling at the time limit"
    detail = (f"{len(log):3d} steps, closest to handle {dist.min():.3f} m (step {int(dist.argmin())}), fingers close at "
              f"{closes[:2]} ({[round(float(dist[t]), 3) for t in closes[:2]]} m), reopen at {opens_again[:3]}, "
              f"door min {door.min():+.2f} rad (open < {DOOR_OPEN}), end ee-handle {dist[-1]:.3f} m")
    return kind, detail


def main() -> None:
    from lerobot_pdp.benchmark.evaluation import evaluate_scene0
    from lerobot_pdp.benchmark.rollouts import run_rollouts
    from lerobot_pdp.benchmark.settings import methods_for
    from lerobot_pdp.benchmark.training import load_run
    from lerobot_pdp.envs.suite import get_suite_env

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a benchmark run directory <out>/runs/<method>/seed<k> (pretrained_model/, eval.json)")
    ap.add_argument("--scene", type=int, default=0, choices=(0, 1, 2, 3))
    ap.add_argument("-n", type=int, default=40, help="rollouts (the benchmark's: 40)")
    ap.add_argument("--seed", type=int, help="the training seed the run was evaluated with (default: from eval.json)")
    ap.add_argument("--episode-latents", action="store_true",
                    help="scene 0: condition rollout i on training demonstration i's encoded latent (PDP)")
    ap.add_argument("--reach", type=float, default=0.04, help="end effector within this of the handle = at the handle (m)")
    args = ap.parse_args()

    suite = get_suite_env("kitchen-microwave")
    method = methods_for(suite).get(args.run.parent.name)
    if method is None:
        ap.error(f"{args.run} is not <out>/runs/<method>/seed<k> with a benchmark method, "
                 f"one of {sorted(methods_for(suite))}")
    if not (args.run / "eval.json").is_file():
        ap.error(f"{args.run} has no eval.json: run the benchmark on it first (its seed and fitted latents are read from there)")
    meta = json.loads((args.run / "eval.json").read_text())
    seed = meta["seed"] if args.seed is None else args.seed
    envs = install_step_log()
    policy, pre, post = load_run(args.run)
    if args.episode_latents:
        if args.scene != 0 or not method.steerable:
            ap.error("--episode-latents needs --scene 0 and a latent-conditioned PDP run")
        train_cfg = json.loads((args.run / "pretrained_model" / "train_config.json").read_text())
        root = Path(train_cfg["dataset"]["root"])
        labels = []
        for ep in range(args.n):  # one env at a time: the active latent is shared by a vectorised rollout
            policy.set_latent(policy.encode((root, ep)))
            run_rollouts(suite, 0, policy, pre, post, 1, seed * 10_000 + ep)
            labels.append(f"ep {ep}")
    elif args.scene == 0:  # the protocol's own scene-0 evaluation (mode means and their seeds, or sampling)
        labels = [r.label for r in evaluate_scene0(suite, method, policy, pre, post, args.n, seed * 10_000).results]
    else:
        if method.adapt != "fit_latent":
            ap.error("scenes 1-3 replay PDP's fitted latent; other methods adapt their weights or noise")
        demo_clearance(args.run.parents[2], args.scene)
        policy.set_latent(torch.tensor(meta["scenes"][str(args.scene)]["z"], dtype=torch.float32))
        run_rollouts(suite, args.scene, policy, pre, post, args.n, seed * 10_000 + args.scene)
        labels = [f"scene {args.scene}"] * args.n

    tally: Counter[str] = Counter()
    by_label: dict[str, Counter[str]] = {}
    for i, (env, label) in enumerate(zip(envs, labels, strict=True)):
        kind, detail = classify(env.diag_log, env.diag_info, args.reach)
        tally[kind] += 1
        by_label.setdefault(label, Counter())[kind] += 1
        print(f"{i:2d} {label:8s} {kind:32s} {detail}", flush=True)
    print(f"scene {args.scene}: {dict(tally)}")
    if len(by_label) > 1:
        for label, c in by_label.items():
            print(f"  {label}: {dict(c)}")


if __name__ == "__main__":
    main()
