"""Does a served PDP keep its steered route when its chunks are spliced just in time? LeRobot's asynchronous
inference emulated in a synchronous loop, so that the splices are the same in every run and the machine's load
does not move them.

Under ``python -m lerobot_pdp.policy_server`` (just in time) a chunk is planned from the observation at step s
while the robot still holds the last chunk's actions; it runs ``--delay`` of them while the new chunk is planned,
then the new chunk's. Here LeRobot's rollout loop (10 envs in lockstep) does the same with the policy's history:
the next chunk is planned when the active one holds ``--delay`` + 1 actions (the server's lead: the planning time
in control steps plus one), and replaces it ``--delay`` steps later; the served policy's
:class:`lerobot_pdp.paced_chunks.LastChunk` continues each chunk from the last (``--carry-noise``: its sampler noise
shifted by the steps between them; ``--execution-horizon H``: held to its actions). ``--whole``: each chunk
planned when the last is used up and used at once, as ``select_action`` does. Per-phase latents advance on the
executed actions, as the server counts them.

The policy is steered to each of ``--modes`` in turn (the mode's latent), ``--per-mode`` rollouts each; a rollout
is on its mode when the env's classifier gives the steered mode (``novel``: none of the demonstrated ones).

    .venv/bin/python benchmarks/bench_async_splices.py --checkpoint DIR [--env pick-place] [--scene 0]
        [--modes 0 9 ...] [--per-mode 10] [--seed 1000] (--whole | --delay 3 [--carry-noise] [--execution-horizon H])
        [--out FILE.json]

Prints the running totals per mode and one JSON line at the end (written to FILE.json with the rollouts).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.utils import populate_queues

from lerobot_pdp.benchmark.rollouts import run_rollouts
from lerobot_pdp.benchmark.training import load_policy
from lerobot_pdp.envs.suite import get_suite_env
from lerobot_pdp.paced_chunks import LastChunk


class JustInTimeLoop:
    """``select_action`` for LeRobot's rollout that splices chunks as the served PDP's client does (module docstring)."""

    def __init__(self, policy: Any, delay: int, whole: bool, last: LastChunk) -> None:
        self.policy, self.delay, self.whole, self.last = policy, delay, whole, last
        self.step, self.first, self.chunk, self.pending = 0, 0, None, None
        self._reset = policy.reset

    def reset(self) -> None:
        self._reset()
        self.step, self.first, self.chunk, self.pending = 0, 0, None, None

    def plan(self) -> torch.Tensor:
        """A chunk from the history up to this step: its first action is this step's (the server's t + 1)."""
        p, cfg = self.policy, self.policy.config
        obs_cond = p.model.obs_cond({k: torch.stack(list(p._queues[k]), dim=1) for k in cfg.condition_features})
        self.last.plan(self.step - 1, self.delay)  # as the server announces a chunk, then the served path's sampling
        chunk = self.last.sample(p, obs_cond, p.current_latent(obs_cond.shape[0], obs_cond.device), None)
        return chunk[:, cfg.n_obs_steps - 1 : cfg.n_obs_steps - 1 + cfg.n_action_steps]

    @torch.no_grad()
    def select_action(self, batch: dict[str, torch.Tensor], **_: Any) -> torch.Tensor:
        p, s = self.policy, self.step
        p._queues = populate_queues(p._queues, {k: v for k, v in batch.items() if k != "action"})
        if self.pending is not None and self.pending[0] <= s:  # the chunk planned `delay` steps ago arrives
            _, self.first, self.chunk = self.pending
            self.pending = None
        left = self.first + self.chunk.shape[1] - s if self.chunk is not None else 0
        if left <= 0:  # nothing left: planned and used at once (the robot waits for it)
            self.first, self.chunk, self.pending = s, self.plan(), None
        elif not self.whole and self.pending is None and left <= self.delay + 1:
            self.pending = (s + self.delay, s, self.plan())
        action = self.chunk[:, s - self.first]
        p._advance_phase(action, replan=False)  # phases advance on executed actions, as the server counts them
        self.step = s + 1
        return action


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--env", default="pick-place")
    ap.add_argument("--scene", default="0")
    ap.add_argument("--modes", type=int, nargs="+", default=None, help="default: every mode of the checkpoint")
    ap.add_argument("--per-mode", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--whole", action="store_true", help="chunks used whole, planned when the last is used up")
    ap.add_argument("--delay", type=int, default=3, help="control steps a chunk takes to plan")
    ap.add_argument("--carry-noise", action="store_true")
    ap.add_argument("--execution-horizon", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()

    torch.set_num_threads(1)  # a synchronous loop; runs side by side stay independent
    policy, pre, post = load_policy(a.checkpoint)
    policy.eval()
    loop = JustInTimeLoop(policy, 0 if a.whole else a.delay, a.whole, LastChunk(a.carry_noise, a.execution_horizon))
    policy.reset, policy.select_action = loop.reset, loop.select_action
    suite = get_suite_env(a.env)
    scene = int(a.scene) if a.scene.isdigit() else a.scene
    means = policy.mode_latents()
    rows = []
    for m in a.modes if a.modes is not None else sorted(means):
        policy.set_latent(means[m])
        for r in run_rollouts(suite, scene, policy, pre, post, a.per_mode, a.seed + 97 * m, label=f"mode {m}").results:
            rows.append({"mode": m, "classified": r.mode, "success": r.success})
        on = sum(r["classified"] == r["mode"] for r in rows)
        print(f"mode {m}: {on} of {len(rows)} on their mode so far", flush=True)
    summary = {"success": sum(r["success"] for r in rows) / len(rows),
               "on_mode": sum(r["classified"] == r["mode"] for r in rows) / len(rows),
               "novel": sum(r["classified"] < 0 for r in rows), "rollouts": len(rows)}
    args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"args": args, **summary, "rows": rows}) + "\n")
    print(json.dumps({**summary, "args": args}))


if __name__ == "__main__":
    main()
