"""Chunks asked for one observation at a time, at the caller's pace: LeRobot's async policy server.

LeRobot's asynchronous inference (``lerobot.async_inference``) runs the policy in a server process that calls
``predict_action_chunk`` with the latest observation the robot client sent, one frame [B, *frame] without
the history ``select_action`` keeps, whenever the client's action queue runs low. PDP conditions on
``n_obs_steps`` frames, so such an observation joins the policy's own observation history (the one
``select_action`` keeps; the first one fills it, as at an episode's start) and the chunk is conditioned on
that history. Steering tied to ``select_action``'s chunks cannot follow a caller that replans at its own pace:
per-phase latents (advanced on the gripper commands ``select_action`` returns) and fitted chunk noises (one
per ``n_action_steps`` chunk) are refused, as under ``lerobot-rollout``'s RTC engine (:mod:`.realtime_chunking`),
at the first chunk and in live requests (the robot keeps its latent).

LeRobot's async robot client has no episodes. ``pdp_sim`` driven by it marks each observation with its env episode
(:data:`EPISODE_KEY`, ``robots/client_hooks.py``); when the mark changes PDP starts a new episode (``reset``: a fresh
observation history, the default latent drawn anew), as callers of ``select_action`` reset it at ``env.reset()``.
"""

from __future__ import annotations

import functools
from typing import Any

import torch
from lerobot.policies.utils import populate_queues
from torch import Tensor

from .observation_encoder import check_observation
from .realtime_chunking import check_rtc_steering

PACED_ENGINE = "a caller that asks for chunks one observation at a time (LeRobot's async policy server)"
PACED_WAY_OUT = "Serve an adapted checkpoint of one latent (a mode, or `lerobot-pdp adapt --noise none`), or"
check_paced_steering = functools.partial(check_rtc_steering, engine=PACED_ENGINE, way_out=PACED_WAY_OUT,
                                         phases_follow=False)
# pdp_sim's episode mark in the raw observations LeRobot's async client sends, and as the policy gets it, [B] (the
# "observation." prefix takes it through LeRobot's processors)
EPISODE_MARK = "pdp_sim_episode"
EPISODE_KEY = "observation.pdp_sim_episode"


def is_one_frame(batch: dict[str, Tensor], features: dict) -> bool:
    """``batch`` holds one observation [B, *frame] per key, not a history [B, n_obs_steps, *frame] (told by the
    first conditioning key it has)."""
    key = next((k for k in features if k in batch), None)
    return key is not None and batch[key].dim() == 1 + len(features[key].shape)


# Left out of torch.compile's graph (``lerobot-rollout --use_torch_compile`` compiles ``predict_action_chunk``, this
# included): dynamo tracing the deques' mutation did not finish in 30 minutes; run eagerly it is a few stacks.
@torch.compiler.disable
def paced_history(policy: Any, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """The observation history [B, n_obs_steps, *frame] per conditioning key after ``batch``'s one observation
    joins it; steering that needs ``select_action``'s pace is refused first (the module docstring)."""
    features = policy.config.condition_features
    check_observation(batch, features, ("B",))  # a missing key or a frame of another size, named
    if EPISODE_KEY in batch:
        episode = float(batch[EPISODE_KEY].reshape(-1)[0])
        if getattr(policy, "_paced_episode", episode) != episode:
            policy.reset()  # a new env episode: its first chunk sees none of the last one's frames
        policy._paced_episode = episode
    check_paced_steering(policy)
    if policy._steer_file is not None:  # a live request the caller cannot follow is refused, the latent kept
        policy._steer_file.check = check_paced_steering
    policy._queues = populate_queues(policy._queues, {k: batch[k] for k in features})
    return {k: torch.stack(list(policy._queues[k]), dim=1) for k in features}
