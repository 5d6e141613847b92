"""How far the DART noise pushes the expert off its noise-free path (run with route_jitter_dart.diff applied).

Every third training mode, same expert seed with and without noise; prints failures and, per episode, the
largest and the 90th-percentile distance (cm) of a noisy state from the noise-free path.
"""

import gymnasium as gym
import numpy as np

from lerobot_pdp.envs import pick_place as pp
from lerobot_pdp.envs.recording import _rollout

env = gym.make(pp.GYM_ID, scene=0, disable_env_checker=True)
ok, n, devs = 0, 0, []
for mode in range(0, 64, 3):
    paths = []
    for noise in (0.0, pp.NOISE_STD):
        r, c = pp.split_mode(mode)
        expert = pp.PickPlaceExpert(pp.phase_via_points(r, pp.OBSTACLE_A), pp.phase_via_points(c, pp.OBSTACLE_B),
                                    np.random.default_rng([1, mode]), route_jitter=pp.ROUTE_JITTER, noise=noise)
        obs, _, info = _rollout(env, expert, 0)
        paths.append(np.stack([o["agent_pos"] for o in obs]))
    ref, states = paths
    n += 1
    good = info["is_success"] and not info["collided"] and pp.classify_mode(states) == mode
    ok += good
    if not good:
        print("failed: mode", mode, info)
    d = np.linalg.norm(states[:, None, :3] - ref[None, :, :3], axis=-1).min(axis=1)
    devs.append((d.max(), np.percentile(d, 90)))
devs = np.asarray(devs) * 100
print(f"{ok} / {n} succeed; largest distance per episode (cm): median {np.median(devs[:, 0]):.1f}, "
      f"range {devs[:, 0].min():.1f}-{devs[:, 0].max():.1f}; 90th percentile: median {np.median(devs[:, 1]):.1f}")
