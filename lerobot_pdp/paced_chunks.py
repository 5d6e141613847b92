"""Chunks asked for one observation at a time, at the caller's pace: LeRobot's async policy server.

LeRobot's asynchronous inference (``lerobot.async_inference``) runs the policy in a server process that calls
``predict_action_chunk`` with the latest observation the robot client sent, one frame [B, *frame] without
the history ``select_action`` keeps, whenever the client's action queue runs low. PDP conditions on
``n_obs_steps`` frames, so such an observation joins the policy's own observation history (the one
``select_action`` keeps; the first one fills it, as at an episode's start) and the chunk is conditioned on
that history. Planned from alone, those frames would be a chunk apart; ``python -m lerobot_pdp.policy_server``
keeps every observation the client sends and puts the ones just before the planned one in the history first
(:class:`ReceivedFrames`), so its frames are consecutive, as in training, times each chunk from the step after
the observation's (:func:`from_the_next_step`), plans once per chunk, just before the client's queue runs out
(:class:`JustInTime`), and holds each chunk to the last one's actions the client runs meanwhile
(:class:`LastChunk`). Per-phase latents advance on the gripper commands the robot executes: ``python -m
lerobot_pdp.policy_server`` tells the policy the actions the robot executed (:class:`ExecutedActions`), so phases
advance on them, as under ``lerobot-rollout``'s RTC engine (:mod:`.realtime_chunking`); any other paced caller has
them refused. Fitted chunk noises belong to the demonstration's frames (noise j to the frames from
``j * n_action_steps``), and the server plans a chunk when the client's queue runs low, at any step: it tells the
policy each chunk's step in the episode, and the noise is taken aligned to the frames it was fitted to
(:meth:`LastChunk.fitted_noise`); any other paced caller has them refused. Refusals come at the first chunk and in
live requests (the robot keeps its latent).

LeRobot's async robot client has no episodes. ``pdp_sim`` driven by it marks each observation with its env episode
(:data:`EPISODE_KEY`, ``robots/client_hooks.py``); when the mark changes PDP starts a new episode (``reset``: a fresh
observation history, the default latent drawn anew), as callers of ``select_action`` reset it at ``env.reset()``.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from typing import Any

import torch
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.policies.utils import populate_queues
from torch import Tensor

from .observation_encoder import check_observation
from .realtime_chunking import check_rtc_steering, prefix_guide

PACED_ENGINE = "a caller that asks for chunks one observation at a time (LeRobot's async policy server)"
PACED_WAY_OUT = "Serve an adapted checkpoint of one latent (a mode, or `lerobot-pdp adapt --noise none`), or"
# pdp_sim's episode mark in the raw observations LeRobot's async client sends, and as the policy gets it, [B] (the
# "observation." prefix takes it through LeRobot's processors)
EPISODE_MARK = "pdp_sim_episode"
EPISODE_KEY = "observation.pdp_sim_episode"
# why a paced caller other than PDP's server cannot replay fitted chunk noises
PACED_NOISES = ("nothing tells PDP the step of the episode each chunk starts at (`python -m lerobot_pdp.policy_server` "
                "does)")


def episode_of(obs: Any) -> Any:
    """The env episode a ``TimedObservation`` of LeRobot's client is marked with (``pdp_sim``; None: no mark)."""
    return obs.get_observation().get(EPISODE_MARK)


def check_paced_steering(policy: Any) -> None:
    """Refuse steering a paced caller cannot follow (the module docstring): chunk noises unless the policy is told
    each chunk's step, per-phase latents unless it is told the executed actions (``python -m
    lerobot_pdp.policy_server`` tells both)."""
    check_rtc_steering(policy, engine=PACED_ENGINE, way_out=PACED_WAY_OUT,
                       reports_executed=getattr(policy, "_paced_executed", None) is not None,
                       replays_noises=getattr(policy, "_paced_last", None) is not None, noises_why=PACED_NOISES)


class ExecutedActions:
    """The gripper commands the robot of LeRobot's async client executed, counted in the served PDP's phases (a
    policy with gripper phases; without, there is nothing to count).

    The client sends with each observation the timestep of the last action it executed, and executes each
    timestep's action from the latest chunk that planned it (``--aggregate_fn_name=latest_only``; LeRobot's
    default blends it with the chunk before's, 0.7 to 0.3, which the latest's command mostly decides). So the
    server keeps the latest planned gripper command per timestep and, before each chunk, counts those up to the
    observation's timestep, in order. The first actions of a chunk that arrives after their timesteps were executed (from the
    chunk before) are taken from it: a gripper flip is timed off by at most the inference delay."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.commands: dict[int, bool] = {}  # timestep -> the gripper closed in the latest action planned for it
        self.last = -1  # the last timestep counted

    def planned(self, timed_actions: list[Any]) -> None:
        """A chunk the server returns: LeRobot's ``TimedAction``s, actions in the robot's units."""
        cfg = self.policy.config
        for action in timed_actions:
            if action.get_timestep() > self.last:
                closed = float(action.get_action()[cfg.segment_gripper_dim]) > cfg.segment_gripper_threshold
                self.commands[action.get_timestep()] = closed

    def executed_up_to(self, timestep: int) -> None:
        """The client executed every planned action up to ``timestep``: count their gripper commands."""
        cfg = self.policy.config
        for t in sorted(k for k in self.commands if self.last < k <= timestep):
            self.policy.steering.observe(torch.tensor([self.commands.pop(t)]), cfg.phase_switch_steps)
            self.last = t


class ReceivedFrames:
    """The observations LeRobot's async client sent, by timestep, so that each chunk is planned on a history of
    consecutive frames, as PDP was trained (a served policy with ``n_obs_steps`` > 1).

    LeRobot's server plans from one observation per chunk, so the frames of PDP's own history would be a chunk
    apart (the client sends only while its queue runs low). Its client, while low, sends an observation every
    control step, each with the timestep of the last action it executed; the server keeps them all here. An
    observation whose predecessors (timesteps ``t - n_obs_steps + 1 .. t - 1``, the same env episode) were not
    received is not planned from (:meth:`received` says so; the server drops it as it drops one too similar):
    the next one, a control step later, is, with it before it (:meth:`preceding`). A must-go observation (the
    client's queue empty: an episode's first, or a robot that ran out of actions) is planned from at once."""

    KEEP = 16  # timesteps kept behind the newest: a low-queue window is a few steps long (camera frames are large)

    def __init__(self, n_obs_steps: int) -> None:
        self.n_obs_steps = n_obs_steps
        self.frames: dict[int, Any] = {}  # timestep -> the latest TimedObservation sent for it
        self.lock = threading.Lock()  # observations arrive on the server's threads, chunks are planned on another

    def _run_before(self, obs: Any) -> list[Any]:
        t, episode = obs.get_timestep(), episode_of(obs)
        run = []
        for k in range(1, self.n_obs_steps):
            frame = self.frames.get(t - k)
            if frame is None or episode_of(frame) != episode:
                break
            run.append(frame)
        return run[::-1]

    def received(self, obs: Any) -> bool:
        """Keep ``obs``; whether it may be planned from now (its predecessors were received, or it must go)."""
        t = obs.get_timestep()
        with self.lock:
            self.frames[t] = obs
            for k in [k for k in self.frames if k < t - self.KEEP]:
                del self.frames[k]
            return bool(obs.must_go) or len(self._run_before(obs)) == self.n_obs_steps - 1

    def preceding(self, obs: Any) -> list[Any]:
        """The observations received for the timesteps just before ``obs``'s, oldest first, up to ``n_obs_steps - 1``
        of them, stopping at the first one missing."""
        with self.lock:
            return self._run_before(obs)


class JustInTime:
    """When a served PDP plans its next chunk: from the observation sent when the client holds no more actions
    than a chunk takes to plan, so that it arrives as the last one runs out (a served PDP with LeRobot's client).

    LeRobot's server plans from every observation that passes its similarity filter, and its client sends one
    every control step while its queue is low: when the robot's state passes the filter (joint degrees), the
    server plans back to back, from the newest observation each time it returns a chunk, and the robot executes
    two or three actions of each (pick-place at 50 fps: 50-65 % success, 97.5-100 % under ``select_action``).
    With states in metres or radians the filter holds nearly every observation until the client's queue is empty,
    and the robot waits for each chunk. A served PDP plans instead, as ``select_action`` does, once per chunk,
    with no regard to that filter; when it plans is set by how long its last chunks took (the median of the last
    :attr:`KEEP`, in control steps, plus :attr:`SLACK`); a chunk late all the same empties the client's queue, and
    its must-go observation is planned from at once."""

    KEEP = 5  # chunks whose planning time sets the lead
    SLACK = 1  # control steps of margin: the client's loop and the channel

    def __init__(self, dt: float) -> None:
        self.dt = dt  # seconds per control step (the server's --fps)
        self.planned_until: int | None = None  # the last timestep a planned chunk has an action for
        self.planned_from: tuple[int, Any] | None = None  # (timestep, env episode) of the last observation planned from
        self.seconds: list[float] = []  # how long the last chunks took to plan
        self.lock = threading.Lock()  # observations arrive on the server's threads, chunks are planned on another

    def delay(self) -> int:
        """Control steps a chunk takes to plan: the lower median of the last :attr:`KEEP` (not the first's warm-up)."""
        with self.lock:
            seconds = sorted(self.seconds)
        took = seconds[(len(seconds) - 1) // 2] if seconds else 0.0
        return math.ceil(took / self.dt - 1e-9)

    def lead(self) -> int:
        """Control steps before the client's queue runs out at which the next chunk is planned."""
        return self.delay() + self.SLACK

    def due(self, obs: Any) -> bool:
        """Whether the next chunk is planned from ``obs`` (not a must-go one): the client holds at most
        :meth:`lead` actions after its timestep, and no chunk is planned from a later one yet."""
        with self.lock:
            until = self.planned_until
        return until is not None and until - obs.get_timestep() <= self.lead()

    def repeats(self, obs: Any) -> bool:
        """Whether ``obs`` is of the timestep (and env episode) of the last observation planned from: the client sent
        it again, no action executed since (a must-go one, after its queue stayed empty: ``pdp_sim`` drops a chunk
        planned before its scene reset), and the chunk planned from the first answers it."""
        with self.lock:
            return self.planned_from == (obs.get_timestep(), episode_of(obs))

    def planning(self, obs: Any, actions: int) -> None:
        """A chunk of ``actions`` actions is planned from ``obs``: its actions follow the observation's timestep, so
        later observations wait for its end."""
        with self.lock:
            self.planned_until = obs.get_timestep() + actions
            self.planned_from = (obs.get_timestep(), episode_of(obs))

    def planned(self, chunk: list[Any], seconds: float) -> None:
        """The chunk returned (``TimedAction``s, timed from the step after the observation's), ``seconds`` in the
        making."""
        with self.lock:
            if chunk:  # a must-go observation may have been planned from since (a later one)
                self.planned_until = max(self.planned_until or -1, chunk[-1].get_timestep())
            self.seconds = [*self.seconds, seconds][-self.KEEP:]


class LastChunk:
    """The served PDP's last chunk by timestep (its actions, normalised, and its sampler noise), from which the next
    chunk continues (a served PDP; :meth:`plan` tells it the timestep each chunk is planned from).

    Planned just in time, a chunk is planned from the observation at timestep t while the client still holds the
    last chunk's actions for t+1 onwards; it runs the first of them while the new one is planned, then the new
    one's (``latest_only``). Each chunk is a sample of a multimodal policy, and two samples need not take the same
    route: with a fresh one spliced in every few steps the robot's route left the demonstrated ones in 15-22 % of
    pick-place's episodes (docs/performance.md). So:

    * ``execution_horizon`` > 0 (``async_execution_horizon``, 5): the new chunk is held to the last one's actions
      after t, weight 1 over the ``delay`` actions the client runs while it is planned, then fading to free at
      ``execution_horizon``, as lerobot-rollout's RTC engine holds PDP's chunks
      (:func:`lerobot_pdp.realtime_chunking.prefix_guide`);
    * ``carry_noise`` (``async_carry_noise``, off): the new chunk's sampler noise is the last one's shifted by the
      steps between their first actions (fresh rows only for the steps the last one did not reach); DDIM is
      deterministic, so the same noise under the next observation tends to the same route.

    A chunk of another episode than the last one's, or one the server did not announce, starts afresh. Fitted chunk
    noises come before a carried noise, taken by the episode's step (:meth:`fitted_noise`); noise the caller gives
    is kept."""

    def __init__(self, carry_noise: bool, execution_horizon: int) -> None:
        self.carry_noise = carry_noise
        self.rtc = RTCConfig(enabled=True, execution_horizon=execution_horizon) if execution_horizon > 0 else None
        self.at: tuple[int, int] | None = None  # (timestep planned from, actions run meanwhile) of the next chunk
        # (policy resets, the first action's timestep, actions [B, n, A], sampler noise [B, horizon, A])
        self.kept: tuple[int, int, Tensor, Tensor] | None = None
        self.episode: tuple[int, int] | None = None  # (policy resets, timestep its first chunk was planned from)

    def plan(self, timestep: int, delay: int) -> None:
        """The next chunk is planned from the observation at ``timestep``; ``delay`` actions run while it is."""
        self.at = (timestep, delay)

    def _advanced(self, policy: Any) -> int | None:
        """Steps from the last chunk's first action to the next one's (None: not of the same episode, or unknown)."""
        if self.at is None or self.kept is None or self.kept[0] != policy.steering.resets:
            return None
        return self.at[0] + 1 - self.kept[1]

    def noise(self, policy: Any, noise: Tensor | None, batch_size: int, device: Any) -> Tensor:
        """The next chunk's sampler noise: ``noise`` (the caller's), else the fitted chunk noises' at the episode's
        step (:meth:`fitted_noise`), else the last one's carried, else fresh."""
        if self.at is not None and (self.episode is None or self.episode[0] != policy.steering.resets):
            self.episode = (policy.steering.resets, self.at[0])  # the episode's first chunk
        if noise is None:
            noise = self.fitted_noise(policy, batch_size, device)
        if noise is None:
            cfg = policy.config
            noise = torch.randn(batch_size, cfg.horizon, policy.action_dim, device=device)
            k = self._advanced(policy) if self.carry_noise else None
            if k is not None and 0 <= k < cfg.horizon and len(self.kept[3]) == batch_size:
                noise = torch.cat([self.kept[3][:, k:].to(noise), noise[:, cfg.horizon - k :]], dim=1)
        return noise

    def fitted_noise(self, policy: Any, batch_size: int, device: Any) -> Tensor | None:
        """The fitted chunk noises (None: none) for a chunk whose first action is the episode's step k: noise
        ``j = k // n_action_steps`` (fitted to the demonstration's frames from ``j * n_action_steps``) shifted by
        ``k - j * n_action_steps`` rows, so each row meets the frame it was fitted to, the rows past its end from
        noise ``j + 1`` (fresh after the last); past the last noise, the last one (it repeats, as in
        ``select_action``)."""
        fitted = policy.steering.noises
        if len(fitted) == 0 or self.at is None or self.episode is None:
            return None
        cfg, n = policy.config, policy.config.n_action_steps
        k = self.at[0] - self.episode[1]
        j, shift = divmod(k, n)
        if j >= len(fitted):
            return fitted.at(j, batch_size, device)
        head = fitted.at(j, batch_size, device)[:, shift:]
        tail = (fitted.at(j + 1, batch_size, device)[:, cfg.horizon - n : cfg.horizon - n + shift]
                if j + 1 < len(fitted) else torch.randn(batch_size, shift, policy.action_dim, device=device))
        return torch.cat([head, tail], dim=1)

    def guide(self, policy: Any, batch_size: int) -> Any:
        """The x0 edit holding the chunk being planned to the last one's actions after its timestep (None: none)."""
        k = self._advanced(policy) if self.rtc is not None else None
        if k is None or k < 0 or k >= self.kept[2].shape[1]:  # a new episode, or nothing in flight
            return None
        return prefix_guide(policy, self.kept[2][:, k:], self.at[1], batch_size, self.rtc)

    def sample(self, policy: Any, obs_cond: Tensor, z: Tensor, noise: Tensor | None) -> Tensor:
        """The chunk [B, horizon, A] (normalised) for ``obs_cond``, ``z``, continuing the last one (:meth:`noise`,
        :meth:`guide`); its actions are kept for the next."""
        noise = self.noise(policy, noise, len(z), obs_cond.device)
        chunk = policy.generate(obs_cond, z, noise=noise, guide=self.guide(policy, len(z)))
        start = policy.config.n_obs_steps - 1
        self.keep(policy, chunk[:, start : start + policy.config.n_action_steps], noise)
        return chunk

    def keep(self, policy: Any, actions: Tensor, noise: Tensor) -> None:
        """The chunk planned (actions [B, n, A], normalised; its first for the step after the observation's)."""
        self.kept = (policy.steering.resets, self.at[0] + 1, actions, noise) if self.at is not None else None
        self.at = None

    def sent(self, actions: int) -> None:
        """The server sends only the chunk's first ``actions``: the rest never reach the client."""
        if self.kept is not None:
            resets, first, kept, noise = self.kept
            self.kept = (resets, first, kept[:, :actions], noise)


def from_the_next_step(chunk: list[Any], dt: float) -> list[Any]:
    """A chunk LeRobot's server timed (``TimedAction``s), its first action given the step after the observation's.

    LeRobot's client sends an observation with the timestep of the last action it executed, taken after that
    action; LeRobot's server gives the chunk's first action that same timestep, so the client drops it as done and
    executes every later one a step early. PDP's chunk starts with the action for the step after the observation
    (as ``select_action`` executes it): labelled so, the client executes each at its step. (Measured on the kitchen
    served on consecutive frames: 60 % of 40 episodes a step early, 100 % of 40 at their steps, against 100 % under
    ``select_action``: docs/performance.md.)"""
    return [dataclasses.replace(a, timestamp=a.get_timestamp() + dt, timestep=a.get_timestep() + 1) for a in chunk]


def precede_history(policy: Any, frames: list[dict[str, Tensor]]) -> None:
    """Make ``frames`` (preprocessed observations [B, *frame], oldest first) the last ones of the policy's
    observation history, which the next observation given one frame at a time then joins."""
    if not frames:
        return
    for key in policy.config.condition_features:
        policy._queues[key].clear()
    for frame in frames:  # the first fills the history (populate_queues), as at an episode's start
        policy._queues = populate_queues(policy._queues, {k: frame[k] for k in policy.config.condition_features})


def is_one_frame(batch: dict[str, Tensor], features: dict) -> bool:
    """``batch`` holds one observation [B, *frame] per key, not a history [B, n_obs_steps, *frame] (told by the
    first conditioning key it has)."""
    key = next((k for k in features if k in batch), None)  # not a tensor: refused as one frame would be
    return key is not None and (not isinstance(batch[key], Tensor) or batch[key].dim() == 1 + len(features[key].shape))


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
