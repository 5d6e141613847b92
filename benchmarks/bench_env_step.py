"""Env step time of every env in the suite: one JSON line per env on stdout.

Measures ``env.step`` through ``gym.make`` (wrappers included, no rendering) with the scripted expert of
mode 0 choosing the actions, so the timed steps are a realistic mix of free motion and near-obstacle
motion; expert time is excluded. Episodes restart on termination.

    .venv/bin/python benchmarks/bench_env_step.py [--steps 2000] [--envs reach-around avoiding]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings

import numpy as np


def bench(env_name: str, steps: int, seed: int = 0) -> dict:
    import gymnasium as gym

    from lerobot_pdp.envs import get_suite_env

    suite = get_suite_env(env_name)
    t0 = time.perf_counter()
    env = gym.make(suite.gym_id, scene=0, disable_env_checker=True)
    make_s = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    step_times, reset_times, episodes = [], [], 0
    obs = None
    expert = None
    done = True
    while len(step_times) < steps:
        if done:
            t = time.perf_counter()
            obs, _ = env.reset(seed=int(rng.integers(2**31 - 1)))
            reset_times.append(time.perf_counter() - t)
            expert = suite.make_expert(episodes % suite.n_modes, rng, scene=0)
            expert.reset(obs)
            episodes += 1
        action = expert(obs)
        t = time.perf_counter()
        obs, _, terminated, truncated, _ = env.step(action)
        step_times.append(time.perf_counter() - t)
        done = terminated or truncated
    env.close()
    st = np.asarray(step_times) * 1e6
    return {
        "env": suite.name,
        "gym_id": suite.gym_id,
        "steps": len(step_times),
        "episodes": episodes,
        "step_us_mean": round(float(st.mean()), 1),
        "step_us_median": round(float(np.median(st)), 1),
        "step_us_p95": round(float(np.percentile(st, 95)), 1),
        "reset_ms_mean": round(float(np.mean(reset_times)) * 1e3, 3),
        "make_s": round(make_s, 3),
        "control_hz": suite.fps,
        "realtime_factor": round((1.0 / suite.fps) / (float(st.mean()) * 1e-6), 1),
    }


def main(argv: list[str] | None = None) -> int:
    warnings.filterwarnings("ignore")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=2000, help="timed steps per env")
    p.add_argument("--envs", nargs="*", default=None, help="suite env names (default: all)")
    args = p.parse_args(argv)
    if args.steps < 1:
        p.error(f"--steps must be >= 1, got {args.steps}")

    import lerobot_pdp.envs as envs
    from lerobot_pdp.benchmark.machine import cpu_model

    names = args.envs or list(envs.SUITE)
    failed = 0
    for name in names:
        try:
            row = bench(name, args.steps)
        except Exception as e:  # noqa: BLE001 - one broken env must not hide the others' numbers
            row = {"env": name, "error": f"{type(e).__name__}: {e}"}
            failed += 1
        row["machine"] = f"{platform.machine()} {platform.processor() or ''}".strip()
        row["cpu"] = cpu_model()
        print(json.dumps(row), flush=True)
    return 1 if failed else 0  # the others' numbers are printed, but a broken env fails the run


if __name__ == "__main__":
    sys.exit(main())
