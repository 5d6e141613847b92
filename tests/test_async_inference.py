"""PDP under LeRobot's asynchronous inference: ``python -m lerobot_pdp.policy_server`` with LeRobot's own robot
client (``python -m lerobot.async_inference.robot_client``) driving a ``pdp_sim`` robot.

The fast tests run LeRobot's server and client classes in this process over a real gRPC channel, with a
checkpoint of an older release (``tests/data/pdp_checkpoints_v2``, small and barely trained: they check the
plumbing, not the behaviour); the slow test runs both commands as processes and steers with a recording.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import subprocess
import sys
import threading
import time
import types
from concurrent import futures
from pathlib import Path

import pytest
import torch
from policies import small_policy

from lerobot_pdp import PDPPolicy, policy_server
from lerobot_pdp.paced_chunks import PACED_ENGINE, PACED_WAY_OUT
from lerobot_pdp.robots import PDPSimConfig, client_hooks
from lerobot_pdp.steering import paced_caller

CHECKPOINTS = Path(__file__).parent / "data" / "pdp_checkpoints_v2"


def _import_in(folder: Path, name: str):
    """LeRobot's async modules, when imported, open a log file under ./logs and reset the root logger (its level,
    its handlers): imported from ``folder``, the root logger put back after, so that later tests' log captures
    see what they expect."""
    import importlib
    import logging

    root = logging.getLogger()
    level, handlers = root.level, root.handlers[:]
    cwd = Path.cwd()
    os.chdir(folder)
    try:
        return importlib.import_module(name)
    finally:
        os.chdir(cwd)
        root.setLevel(level)
        root.handlers[:] = handlers


@pytest.fixture
def server_module(monkeypatch, tmp_path):
    """LeRobot's policy-server module; what ``admit_pdp`` changes in it is restored after the test."""
    server = _import_in(tmp_path, "lerobot.async_inference.policy_server")

    for name in ("SUPPORTED_POLICIES", "raw_observation_to_observation", "get_policy_class"):
        monkeypatch.setattr(server, name, getattr(server, name))
    for name in ("_predict_action_chunk", "_enqueue_observation", "SendPolicyInstructions", "GetActions"):
        monkeypatch.setattr(server.PolicyServer, name, getattr(server.PolicyServer, name))
    return server


@pytest.fixture
def client_module(monkeypatch, tmp_path):
    """LeRobot's robot-client module with pdp_sim's hooks; restored after the test."""
    robot_client = _import_in(tmp_path, "lerobot.async_inference.robot_client")

    for name in ("map_robot_keys_to_lerobot_features", "RobotClient", "async_client"):
        monkeypatch.setattr(robot_client, name, getattr(robot_client, name))
    client_hooks.FAILURES.clear()  # a run's failures are the run's own
    assert client_hooks.install()
    yield robot_client
    client_hooks.FAILURES.clear()
    from lerobot_pdp.robots.pdp_sim import _LIVE

    for robot in list(_LIVE.values()):
        if robot.is_connected:
            robot.disconnect()
    _LIVE.clear()


def _outcomes(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


# ------------------------------------------------------------------------------------ one observation at a time


def _policy_frames_and_noise(meta):
    """A small PDP in eval mode, three random one-observation frames [1, *frame] and one sampler noise."""
    p = small_policy(meta)
    p.eval()
    g = torch.Generator().manual_seed(0)
    frames = [{k: torch.rand(1, *ft.shape, generator=g) for k, ft in p.config.condition_features.items()}
              for _ in range(3)]
    return p, frames, torch.randn(1, p.config.horizon, p.action_dim, generator=g)


def test_one_observation_at_a_time_joins_the_policy_history(synthetic_meta):
    """What the server passes (one frame [B, D] per chunk) conditions PDP as select_action's history does: the
    frames it was given, newest last; the first one fills the history."""
    p, frames, noise = _policy_frames_and_noise(synthetic_meta)

    def history(*idx):
        return {k: torch.stack([frames[i][k] for i in idx], dim=1) for k in p.config.condition_features}

    p.reset()
    first = p.predict_action_chunk(frames[0], noise=noise)
    torch.testing.assert_close(first, p.predict_action_chunk(history(0, 0), noise=noise))
    p.predict_action_chunk(frames[1], noise=noise)
    third = p.predict_action_chunk(frames[2], noise=noise)
    torch.testing.assert_close(third, p.predict_action_chunk(history(1, 2), noise=noise))
    assert not torch.allclose(first, third)

    # pdp_sim's episode mark (LeRobot's client has no episodes): a new mark starts a new episode, whose first
    # chunk sees none of the last episode's frames
    from lerobot_pdp.paced_chunks import EPISODE_KEY

    def marked(i, episode):
        return {**frames[i], EPISODE_KEY: torch.tensor([float(episode)])}

    p.reset()
    resets = p.steering.resets
    p.predict_action_chunk(marked(0, 0), noise=noise)
    same = p.predict_action_chunk(marked(1, 0), noise=noise)
    torch.testing.assert_close(same, p.predict_action_chunk(history(0, 1), noise=noise))
    assert p.steering.resets == resets  # the same episode
    new = p.predict_action_chunk(marked(2, 1), noise=noise)
    torch.testing.assert_close(new, p.predict_action_chunk(history(2, 2), noise=noise))
    assert p.steering.resets == resets + 1


def test_the_server_plans_each_chunk_on_consecutive_frames_the_client_sent(synthetic_meta):
    """LeRobot's server plans from one observation per chunk, a chunk apart; PDP's history must be consecutive
    frames, as trained. An observation whose predecessors were not sent waits for the next one (unless it must
    go); the frames before it then join the history, oldest first, within one env episode."""
    from lerobot.async_inference.helpers import TimedObservation

    from lerobot_pdp.paced_chunks import EPISODE_MARK, ReceivedFrames, precede_history

    def obs(t: int, must_go: bool = False, episode: int = 0) -> TimedObservation:
        o = TimedObservation(timestamp=0.0, timestep=t, observation={"x": float(t), EPISODE_MARK: float(episode)})
        o.must_go = must_go
        return o

    frames = ReceivedFrames(n_obs_steps=3)
    assert frames.received(obs(0, must_go=True)) and frames.preceding(obs(0)) == []  # an episode's first
    assert not frames.received(obs(4)) and not frames.received(obs(5))  # 3 (and 2) were not sent
    assert frames.received(obs(6))
    assert [o.get_timestep() for o in frames.preceding(obs(6))] == [4, 5]
    assert frames.received(obs(7, must_go=True)) and len(frames.preceding(obs(7))) == 2
    assert not frames.received(obs(8, episode=1))  # 6 and 7 were another episode's
    assert frames.received(obs(9, must_go=True, episode=1))
    assert [o.get_timestep() for o in frames.preceding(obs(9, episode=1))] == [8]
    frames.received(obs(9 + ReceivedFrames.KEEP + 1, must_go=True, episode=1))
    assert min(frames.frames) > 9  # old timesteps are let go

    p, f, noise = _policy_frames_and_noise(synthetic_meta)
    p.reset()
    p.predict_action_chunk(f[0], noise=noise)  # the history the last chunk left: frame 0
    precede_history(p, [f[1]])
    planned = p.predict_action_chunk(f[2], noise=noise)
    history = {k: torch.stack([f[1][k], f[2][k]], dim=1) for k in p.config.condition_features}
    torch.testing.assert_close(planned, p.predict_action_chunk(history, noise=noise))


def test_steering_a_paced_caller_cannot_follow_is_refused(synthetic_meta):
    """Fitted chunk noises replay one per select_action chunk: asked for chunks at its own pace, PDP refuses
    them with the way out, before acting."""
    p = small_policy(synthetic_meta)
    p.eval()
    p.fit_latent((synthetic_meta.root, 2), steps=1, noise="chunks")
    frame = {k: torch.zeros(1, *ft.shape) for k, ft in p.config.condition_features.items()}
    with pytest.raises(ValueError, match=r"fitted chunk noises.*async policy server.*Serve an adapted checkpoint"):
        p.predict_action_chunk(frame)


# ------------------------------------------------------------------------------------------------- the server


def test_the_server_admits_pdp_and_passes_the_environment_state(server_module):
    server = server_module
    policy_server.admit_pdp(server, [])
    assert "pdp" in server.SUPPORTED_POLICIES and "diffusion" in server.SUPPORTED_POLICIES
    state, env = ["x", "y"], ["ox", "oy", "oz"]
    features = {"observation.state": {"dtype": "float32", "shape": (2,), "names": state},
                "observation.environment_state": {"dtype": "float32", "shape": (3,), "names": env}}
    raw = {"x": 1.0, "y": 2.0, "ox": 3.0, "oy": 4.0, "oz": 5.0}
    obs = server.raw_observation_to_observation(raw, features, {})
    torch.testing.assert_close(obs["observation.state"], torch.tensor([[1.0, 2.0]]))
    torch.testing.assert_close(obs["observation.environment_state"], torch.tensor([[3.0, 4.0, 5.0]]))
    with pytest.raises(KeyError, match=r"lacks \['oz'\] of 'observation.environment_state'"):
        server.raw_observation_to_observation({k: v for k, v in raw.items() if k != "oz"}, features, {})


def test_the_server_loads_pdp_with_its_policy_options_and_replays_chunk_noises(server_module, tmp_path, caplog):
    from lerobot_pdp.steering import write_steering

    server = server_module
    steer = tmp_path / "steer.json"
    policy_server.admit_pdp(server, ["--steer_mode=1", f"--steer_file={steer}"])
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.policy_server"):
        policy = server.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "trained"))
    assert f"with --policy.steer_mode=1 --policy.steer_file={steer}" in caplog.text  # the options as typed
    modes = policy.mode_latents()
    torch.testing.assert_close(policy.active_latent, modes[1].reshape(1, -1))
    write_steering(steer, {"mode": 2})  # live steering of the served policy: read before the next chunk
    frame = {k: torch.zeros(1, *ft.shape) for k, ft in policy.config.condition_features.items()}
    policy.predict_action_chunk(frame)
    torch.testing.assert_close(policy.active_latent, modes[2].reshape(1, -1))
    # adapted with --noise chunks: served, the episode's first chunk from its first noise (the server announces it)
    policy_server.admit_pdp(server, [])
    policy = server.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "adapted"))
    assert len(policy.steering.noises) > 0
    policy._paced_last.plan(7, 0)
    policy.predict_action_chunk(frame)
    torch.testing.assert_close(policy._paced_last.kept[3][0], policy.steering.noises.noise[0])


def test_a_start_up_fit_of_phases_and_chunk_noises_runs_on_the_server_and_is_refused_elsewhere(server_module, tmp_path, monkeypatch):
    """The server tells the policy the actions the client executed and each chunk's step, so a start-up fit of a
    latent per gripper phase, with chunk noises, runs; under a paced caller that does not, it is refused before the
    fit's seconds to minutes, with the way out."""
    from lerobot_pdp.envs.recording import make_dataset

    server = server_module
    demo = make_dataset(env="pick-place", out=tmp_path / "pick", scene=0, episodes_per_mode=1, seed=0, modes=[0],
                        progress=False)
    policy_server.admit_pdp(server, [f"--steer_dataset_root={demo}", "--steer_episode_index=0", "--fit_noise=chunks",
                                     "--fit_steps=2", "--fit_noise_steps=1"])
    policy = server.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "adapted_pick_place"))
    assert policy.steering.per_phase and policy._paced_executed is not None and len(policy.steering.noises) > 0
    monkeypatch.setattr(PDPPolicy, "fit_latent", lambda *a, **k: pytest.fail("fitted before refusing"))
    with paced_caller(PACED_ENGINE, PACED_WAY_OUT):  # a paced caller that does not report them
        with pytest.raises(ValueError, match=r"fit_noise=chunks fits one sampler noise .*async policy server.*Serve "
                                             r"an adapted checkpoint.* --policy.fit_noise=none"):
            PDPPolicy.from_pretrained(str(CHECKPOINTS / "adapted_pick_place"), config=policy.config)
        policy.config.fit_noise = "none"
        with pytest.raises(ValueError, match=r"episode 0 splits into [2-9] gripper phases, .*async policy server"):
            PDPPolicy.from_pretrained(str(CHECKPOINTS / "adapted_pick_place"), config=policy.config)


def test_a_served_pdp_plans_each_chunk_just_in_time():
    """LeRobot's server plans from every observation past its similarity filter; its client sends one every step
    while its queue is low, so a robot whose state passes the filter got a chunk every inference time, each mostly
    dropped. A served PDP plans once per chunk, when the client holds no more actions than the last chunks took
    to plan (their median, in control steps, plus one), whatever the filter says; a must-go one goes at once,
    unless the client sent the observation planned from again. ``async_just_in_time=false``: whole chunks, planned
    from an empty queue only."""
    import queue

    from lerobot.async_inference.helpers import TimedAction, TimedObservation

    from lerobot_pdp.paced_chunks import EPISODE_MARK, JustInTime, ReceivedFrames

    def obs(t: int, must_go: bool = False, episode: int = 0) -> TimedObservation:
        o = TimedObservation(timestamp=0.0, timestep=t, observation={EPISODE_MARK: float(episode)})
        o.must_go = must_go
        return o

    def chunk(t: int) -> list:  # PDP's, timed from the step after its observation's
        return [TimedAction(timestamp=0.0, timestep=t + 1 + i, action=torch.zeros(2)) for i in range(8)]

    timing = JustInTime(dt=0.02)
    assert not timing.due(obs(3)) and timing.lead() == 1  # nothing planned: a must-go observation starts
    timing.planning(obs(0), 8)
    assert not timing.due(obs(6)) and timing.due(obs(7))  # 1 action left: the slack alone
    timing.planned(chunk(0), 0.05)  # 2.5 control steps
    assert timing.lead() == 4 and timing.due(obs(4)) and not timing.due(obs(3))
    timing.planning(obs(4), 8)
    assert not timing.due(obs(5))  # that chunk is the next one, until 12
    for seconds in (0.5, 0.05, 0.05, 0.05):  # one slow chunk does not set the lead
        timing.planned(chunk(4), seconds)
    assert timing.lead() == 4 and timing.planned_until == 12

    filtered = []  # what reached LeRobot's enqueue (its similarity filter)

    def lerobots(self, o) -> bool:
        filtered.append(o.get_timestep())
        self.observation_queue.put(o)
        return True

    enqueue = policy_server.with_paced_observations(lerobots)
    policy = types.SimpleNamespace(config=types.SimpleNamespace(n_action_steps=8, async_just_in_time=True),
                                   _paced_frames=ReceivedFrames(2))
    server = types.SimpleNamespace(policy=policy, policy_type="pdp", actions_per_chunk=10,
                                   config=types.SimpleNamespace(environment_dt=0.02), observation_queue=queue.Queue(1),
                                   _predicted_timesteps={0}, _predicted_timesteps_lock=threading.Lock())
    assert enqueue(server, obs(0, must_go=True)) and filtered == [0]
    server.observation_queue.get()
    policy._paced_timing.planned(chunk(0), 0.05)  # lead 4: chunk 1..8 is planned from at 4
    queued = [t for t in range(1, 8) if enqueue(server, obs(t))]
    assert queued == [4] and filtered == [0]  # 5, 6, 7 wait for chunk 5..12; no filter asked
    assert server.observation_queue.get().get_timestep() == 4 and policy._paced_timing.planned_until == 12
    server._predicted_timesteps.add(8)
    assert not enqueue(server, obs(8)) and server.observation_queue.empty()  # planned from already
    assert enqueue(server, obs(13, must_go=True)) and filtered == [0, 13]  # a late chunk: the queue ran empty
    assert not enqueue(server, obs(13, must_go=True))  # sent again, no action since: the chunk from 13 answers it
    server.observation_queue.get()
    assert enqueue(server, obs(13, must_go=True, episode=1)) and filtered == [0, 13, 13]  # a new episode's first
    server.observation_queue.get()
    policy.config.async_just_in_time = False  # whole chunks: planned only from an empty queue
    assert [t for t in range(14, 22) if enqueue(server, obs(t, episode=1))] == [] and filtered == [0, 13, 13]
    assert enqueue(server, obs(22, must_go=True, episode=1)) and filtered == [0, 13, 13, 22]
    server.observation_queue.get()
    other = types.SimpleNamespace(**{**vars(server), "policy_type": "diffusion"})
    assert enqueue(other, obs(23)) and filtered == [0, 13, 13, 22, 23]  # another policy type: LeRobot's rule


def test_a_served_chunk_continues_the_last_ones_noise_and_can_be_held_to_its_actions(synthetic_meta, server_module):
    """Planned just in time, a chunk is planned from the observation at t while the client still holds the last
    chunk's actions after t and runs the first of them meanwhile. With an execution horizon (the server's default)
    it is held to the last chunk's actions (weight 1 over the delay, then fading), as lerobot-rollout's RTC engine
    holds PDP's chunks; with ``carry_noise`` its sampler noise is the last chunk's, shifted by the steps between
    them (fresh for the steps the last did not reach). A new episode, or a call the server did not announce:
    afresh."""
    from lerobot_pdp.paced_chunks import EPISODE_KEY, LastChunk

    p, frames, noise = _policy_frames_and_noise(synthetic_meta)
    p.set_latent(p.mode_latents()[1])  # not a latent drawn per episode
    cfg, n = p.config, p.config.n_action_steps

    def chunk(last: LastChunk, i: int, plan: tuple[int, int] | None, episode: int = 0, given=None):
        p._paced_last = last  # as the server asks for one: announced, then one frame
        if plan is not None:
            last.plan(*plan)
        return p.predict_action_chunk({**frames[i], EPISODE_KEY: torch.tensor([float(episode)])}, noise=given)

    def free(a: int, b: int, given):  # the chunk on history (frame a, frame b) from noise ``given``, nothing held
        return p.predict_action_chunk({k: torch.stack([frames[a][k], frames[b][k]], dim=1)
                                       for k in cfg.condition_features}, noise=given)

    # the noise carried: the last chunk's, shifted by the steps between their first actions
    carry = LastChunk(carry_noise=True, execution_horizon=0)
    p.reset()
    torch.manual_seed(0)
    first = chunk(carry, 0, (10, 0))
    n1 = carry.kept[3]
    assert carry.kept[1] == 11 and carry.kept[2].shape == (1, n, p.action_dim)  # timed from the step after 10
    torch.testing.assert_close(first, free(0, 0, n1))
    second = chunk(carry, 1, (13, 2))  # its first action is for 14: three steps on
    n2 = carry.kept[3]
    torch.testing.assert_close(n2[:, : cfg.horizon - 3], n1[:, 3:])
    assert not torch.allclose(n2[:, cfg.horizon - 3 :], n1[:, -3:])  # fresh where the last one did not reach
    torch.testing.assert_close(second, free(0, 1, n2))
    chunk(carry, 2, (20, 2), episode=1)  # a new episode: fresh
    assert not torch.allclose(carry.kept[3][:, : cfg.horizon - 7], n2[:, 7:])
    chunk(carry, 2, (21, 2), episode=1, given=noise)  # noise given (or fitted) is kept
    torch.testing.assert_close(carry.kept[3], noise)
    chunk(carry, 0, None, episode=1)
    assert carry.kept is None  # not announced by the server: nothing kept to continue
    fresh = LastChunk(carry_noise=False, execution_horizon=0)
    chunk(fresh, 0, (30, 0), episode=1)
    m1 = fresh.kept[3]
    chunk(fresh, 1, (33, 2), episode=1)
    assert not torch.allclose(fresh.kept[3][:, : cfg.horizon - 3], m1[:, 3:])

    # held to the last chunk's actions (the same noise for both, to tell the hold alone)
    held = LastChunk(carry_noise=False, execution_horizon=3)
    p.reset()
    first = chunk(held, 0, (10, 0), given=noise)
    torch.testing.assert_close(first, free(0, 0, noise))  # nothing before it
    second = chunk(held, 1, (13, 2), given=noise)  # the client holds 14..18 of the first, runs 14, 15 meanwhile
    torch.testing.assert_close(second[:, :2], first[:, 3:5])  # exactly what the robot runs while it is planned
    unheld = free(0, 1, noise)
    assert not torch.allclose(unheld[:, :2], first[:, 3:5], atol=1e-2)
    assert (second[:, 2] - first[:, 5]).norm() < (unheld[:, 2] - first[:, 5]).norm()  # fading
    held.sent(5)  # the server sends only five: the rest never reach the client
    assert held.kept[2].shape[1] == 5
    torch.testing.assert_close(chunk(held, 2, (19, 2), given=noise), free(1, 2, noise))  # nothing after 18: free
    torch.testing.assert_close(chunk(held, 2, (20, 2), episode=1, given=noise), free(2, 2, noise))  # a new episode

    # the server makes one for the policy it loads and announces each chunk (the delay JustInTime measures)
    policy_server.admit_pdp(server_module, [])
    last = server_module.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "trained"))._paced_last
    assert not last.carry_noise and last.rtc.execution_horizon == 5  # the defaults
    policy_server.admit_pdp(server_module, ["--async_carry_noise=true", "--async_execution_horizon=0"])
    last = server_module.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "trained"))._paced_last
    assert last.carry_noise and last.rtc is None


def test_fitted_chunk_noises_are_replayed_by_the_episodes_step_aligned_to_their_frames(synthetic_meta):
    """Noise j was fitted to the chunk from the demonstration's step j * n_action_steps; the server plans chunks just
    in time, at any step k: its noise is noise k // n shifted by k mod n rows (each row meets the frame it was fitted
    to), the rows past its end from the next noise, fresh after the last; past the last noise, the last one. The
    steps count from the episode's first chunk; a noise the caller gives is kept."""
    from lerobot_pdp.paced_chunks import LastChunk

    p = small_policy(synthetic_meta)
    p.eval()
    cfg, a = p.config, p.action_dim
    n, h = cfg.n_action_steps, cfg.horizon
    noises = torch.randn(3, h, a, generator=torch.Generator().manual_seed(0))
    p.steering.activate(p.mode_latents()[1], noise=noises)
    last = LastChunk(carry_noise=True, execution_horizon=0)  # fitted noises come before the carried one

    def noise_at(t: int, given=None):  # as the server asks for the chunk planned from timestep t
        last.plan(t, 0)
        x = last.noise(p, given, 1, "cpu")
        last.keep(p, torch.zeros(1, n, a), x)
        return x[0]

    p.reset()
    torch.testing.assert_close(noise_at(40), noises[0])  # the episode's first chunk: step 0
    x = noise_at(40 + n + 3)  # step n + 3: noise 1 three rows on, then noise 2's rows for those steps
    torch.testing.assert_close(x[: h - 3], noises[1, 3:])
    torch.testing.assert_close(x[h - 3 :], noises[2, h - n : h - n + 3])
    x = noise_at(40 + 2 * n + 2)  # noise 2 two rows on, then fresh
    torch.testing.assert_close(x[: h - 2], noises[2, 2:])
    assert not torch.allclose(x[h - 2 :], noises[2, :2])
    torch.testing.assert_close(noise_at(40 + 5 * n + 1), noises[2])  # past the last noise: the last one
    given = torch.ones(1, h, a)
    torch.testing.assert_close(noise_at(40 + 6 * n, given=given), given[0])
    p.reset()  # a new episode: its steps count from its first chunk
    torch.testing.assert_close(noise_at(100), noises[0])
    torch.testing.assert_close(noise_at(100 + n), noises[1])


def test_the_server_counts_the_gripper_commands_the_client_executed_in_the_policys_phases(server_module):
    """LeRobot's client sends the timestep of the last action it executed with each observation and executes each
    timestep's action from the latest chunk planning it: the policy's phases count those commands, in order. PDP's
    chunk is timed from the step after the observation's (LeRobot's server times it from the observation's, and
    its client would skip the first action and run the rest a step early)."""
    from lerobot.async_inference.helpers import TimedAction, TimedObservation

    policy_server.admit_pdp(server_module, ["--steer_mode=0"])  # a mode: one latent per phase
    policy = server_module.get_policy_class("pdp").from_pretrained(str(CHECKPOINTS / "adapted_pick_place"))
    assert policy.steering.per_phase
    cfg = policy.config
    open_, closed = cfg.segment_gripper_threshold - 1.0, cfg.segment_gripper_threshold + 1.0

    def chunk(start: int, grippers: list[float]) -> list:
        actions = []
        for i, g in enumerate(grippers):
            a = torch.zeros(policy.action_dim)
            a[cfg.segment_gripper_dim] = g
            actions.append(TimedAction(timestamp=0.0, timestep=start + i, action=a))
        return actions

    served, planned = [], []

    def predict(self, observation_t):  # stands for LeRobot's: the chunk it returns for this observation
        served.append(observation_t.get_timestep())
        return planned[-1]

    predict_and_count = policy_server.with_paced_policy(predict, server=server_module)
    # what the wrapper reads of LeRobot's PolicyServer
    server = types.SimpleNamespace(policy=policy, policy_type="pdp", config=types.SimpleNamespace(environment_dt=0.02))
    planned.append(chunk(0, [open_] * 8))  # timed 1..8: a chunk starts with the action after its observation
    first = predict_and_count(server, TimedObservation(timestamp=0.0, timestep=0, observation={}))
    assert [a.get_timestep() for a in first] == list(range(1, 9)) and first[0].get_timestamp() == 0.02
    planned.append(chunk(5, [open_] + [closed] * 7))  # replanned at 5: 6..13, closes from 7 on (7, 8 replaced)
    predict_and_count(server, TimedObservation(timestamp=0.0, timestep=5, observation={}))
    assert policy._paced_executed.last == 5 and int(policy.steering.phases.phase[0]) == 0
    predict_and_count(server, TimedObservation(timestamp=0.0, timestep=12, observation={}))  # 6..12 executed
    assert served == [0, 5, 12] and policy._paced_executed.last == 12
    assert int(policy.steering.phases.phase[0]) == 1  # closed for 6 commands, held for phase_switch_steps: carry


@pytest.mark.parametrize("option, said", [
    ("--policy.steer_mod=2", r"unrecognized arguments: --steer_mod=2\) in --policy.steer_mod=2"),
    ("--policy.steer_latent=x", r"`steer_latent`: Could not decode"),
    ("--policy.horizon=0", r"Invalid PDPConfig: horizon must be >= 1"),
])
def test_a_bad_policy_option_stops_the_server_before_it_listens(option, said):
    server_args, overrides = policy_server.split_policy_options(["--port=8080", option])
    assert server_args == ["--port=8080"]
    with pytest.raises(SystemExit, match=r"lerobot_pdp.policy_server: bad --policy.\* option \(" + said):
        policy_server.check_policy_options(overrides)


def test_the_servers_help_names_the_policy_options(capsys):
    with pytest.raises(SystemExit) as done:
        policy_server.main(["--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "--policy.<field>=<value> of PDPConfig" in out and "--port" in out  # PDP's options, then LeRobot's


def test_a_client_of_another_robot_is_refused_at_connect(synthetic_meta):
    """The features a robot client sends must be the policy's (a camera in (H, W, C) as datasets store it): another
    env's client is refused when it sends its policy instructions, naming each difference, where it used to get no
    action and wait for good (the server failing at every chunk). SendPolicyInstructions is wrapped to check."""
    cfg = small_policy(synthetic_meta).config
    same = {"observation.state": {"dtype": "float32", "shape": (2,)},
            "observation.environment_state": {"dtype": "float32", "shape": (2,)}}
    policy_server.check_client_features(cfg, same)
    other = {**same, "observation.state": {"dtype": "float32", "shape": (4,)}}
    del other["observation.environment_state"]
    with pytest.raises(ValueError, match=r"does not give what the PDP policy needs: 'observation.state' has shape "
                                         r"\(4,\), the policy was trained on \(2,\); lacks 'observation.environment_state' "
                                         r"\(it has observations 'observation.state'\)"
                                         r".*--robot.env"):
        policy_server.check_client_features(cfg, other)
    # a robot naming the same joints in another order than the training data: refused, not read position by position
    swapped = {**same, "observation.state": {"dtype": "float32", "shape": (2,), "names": ["y.pos", "x.pos"]}}
    with pytest.raises(ValueError, match=re.escape("'observation.state' names its values ['y.pos', 'x.pos'], in "
                                                   "another order than the policy's training data (['x', 'y'])")):
        policy_server.check_client_features(cfg, swapped)
    policy_server.check_client_features(cfg, {**same, "observation.state": {"dtype": "float32", "shape": (2,),
                                                                            "names": ["x.pos", "y.pos"]}})
    from lerobot.async_inference import policy_server as server

    policy_server.admit_pdp(server, [])
    assert getattr(server.PolicyServer.SendPolicyInstructions, "_lerobot_original", None) is not None


# ------------------------------------------------------------------------------ server and client, in process


@contextlib.contextmanager
def _serving(server, options: list[str] | None = None):
    """LeRobot's policy server admitting PDP (with ``--policy.*`` ``options`` as ``--<field>=...``), over a real
    gRPC channel on a free port: (service, port, the observations it passed to the policy, the gRPC server)."""
    import grpc
    from lerobot.async_inference.configs import PolicyServerConfig
    from lerobot.transport import services_pb2_grpc

    policy_server.admit_pdp(server, options or [])
    seen = []
    passes = server.raw_observation_to_observation
    server.raw_observation_to_observation = lambda *a, **k: (obs := passes(*a, **k), seen.append(obs))[0]
    service = server.PolicyServer(PolicyServerConfig(host="127.0.0.1", fps=50))
    grpc_server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(service, grpc_server)
    port = grpc_server.add_insecure_port("127.0.0.1:0")
    grpc_server.start()
    try:
        yield service, port, seen, grpc_server
    finally:
        grpc_server.stop(0)


def _client_config(port: int, tmp_path: Path, episodes: int = 2, env: str = "reach-around",
                   checkpoint: str = "trained", aggregation: str = "latest_only"):
    from lerobot.async_inference.configs import RobotClientConfig

    return RobotClientConfig(
        policy_type="pdp", pretrained_name_or_path=str(CHECKPOINTS / checkpoint), actions_per_chunk=8,
        server_address=f"127.0.0.1:{port}", fps=100, aggregate_fn_name=aggregation,
        robot=PDPSimConfig(env=env, scene="0", episodes=episodes, outcomes=str(tmp_path / "outcomes.jsonl"),
                           calibration_dir=tmp_path))


def _run_client(client, outcomes: Path) -> None:
    """LeRobot's client threads until the robot ends the run (at most 120 s)."""
    assert client.start()
    receiver = threading.Thread(target=client.receive_actions, daemon=True)
    receiver.start()
    loop = threading.Thread(target=client.control_loop, kwargs={"task": ""}, daemon=True)
    loop.start()  # returns when the robot ends the run
    loop.join(120)
    stalled = loop.is_alive()
    client.stop()  # ends a stalled loop too
    loop.join(10)
    assert not stalled, f"the run did not end within 120 s; episodes ended: {_outcomes(outcomes)}"
    receiver.join(10)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_lerobot_robot_client_drives_pdp_sim_through_the_server_and_ends_after_its_episodes(
        server_module, client_module, tmp_path, monkeypatch):
    """LeRobot's client and server classes over a real gRPC channel: pdp_sim's features reach PDP as trained
    (state and environment state), each chunk is planned on consecutive frames, each episode's end drops the
    queued actions, and the run ends after ``--robot.episodes``."""
    from lerobot_pdp.paced_chunks import ReceivedFrames

    preceded = []  # (must go, timestep, the timesteps of the frames put before it) per chunk
    preceding = ReceivedFrames.preceding
    monkeypatch.setattr(ReceivedFrames, "preceding", lambda self, o: (
        run := preceding(self, o), preceded.append((o.must_go, o.get_timestep(), [f.get_timestep() for f in run])))[0])
    outcomes = tmp_path / "outcomes.jsonl"
    with _serving(server_module) as (service, port, seen, _):
        client = client_module.RobotClient(_client_config(port, tmp_path))
        features = client.policy_config.lerobot_features
        assert features["observation.environment_state"]["names"] == client.robot.env_state_names
        _run_client(client, outcomes)
    # every chunk but an episode's first was planned on the frame just before its own, as in training (the
    # client sends an observation every step once its queue is low; an episode's first has none before it)
    alone = [t for _, t, run in preceded if not run]
    assert len(alone) <= 2 and len(preceded) > 2, preceded
    assert all(run == [t - 1] for _, t, run in preceded if run), preceded
    lines = _outcomes(outcomes)
    assert [d["episode"] for d in lines] == [0, 1] and all(d["ended_by"] != "stopped" for d in lines), lines
    keys = ["observation.environment_state", "observation.pdp_sim_episode", "observation.state", "task"]
    assert seen and all(sorted(obs) == keys for obs in seen)
    marks = [float(obs["observation.pdp_sim_episode"]) for obs in seen]  # each episode's chunks, in order
    assert marks == sorted(marks) and set(marks) == {0.0, 1.0}, marks
    assert service.policy._paced_episode == 1.0  # the served policy followed the episodes
    assert not client_hooks.FAILURES


def test_a_latent_per_gripper_phase_follows_the_commands_the_client_executed(server_module, client_module, tmp_path,
                                                                            monkeypatch):
    """pick-place served with a mode's latent per gripper phase: every chunk the server returns is noted, and the
    commands the client executed reach the policy's phases before the next chunk."""
    from lerobot_pdp.paced_chunks import ExecutedActions

    counted, chunks = [], []
    executed_up_to, planned = ExecutedActions.executed_up_to, ExecutedActions.planned
    monkeypatch.setattr(ExecutedActions, "executed_up_to",
                        lambda self, t: (counted.append((t, self.last)), executed_up_to(self, t))[1])
    monkeypatch.setattr(ExecutedActions, "planned", lambda self, c: (chunks.append(c), planned(self, c))[1])
    outcomes = tmp_path / "outcomes.jsonl"
    with _serving(server_module, ["--steer_mode=0"]) as (service, port, _, _):
        client = client_module.RobotClient(_client_config(port, tmp_path, episodes=1, env="pick-place",
                                                          checkpoint="adapted_pick_place"))
        _run_client(client, outcomes)
    policy = service.policy
    assert policy.steering.per_phase and len(_outcomes(outcomes)) == 1
    assert len(counted) == len(chunks) >= 2  # before every chunk
    assert policy._paced_executed.last > 0  # executed commands were counted
    assert all(t >= last for t, last in counted)  # in order, each once


def test_a_refused_client_leaves_the_one_being_served_alone(server_module, client_module, tmp_path):
    """A client of another robot is refused from the checkpoint's config, before LeRobot loads anything: the
    client already served keeps its policy and features (they were replaced by the refused client's, and its next
    chunk failed naming them), and the refused one ends with the differences named (not a gRPC error dump)."""
    from lerobot_pdp.policy_server import CLIENT_REFUSED

    with _serving(server_module) as (service, port, _, _):
        served = client_module.RobotClient(_client_config(port, tmp_path / "a"))
        try:
            assert served.start()
            policy, features = service.policy, service.lerobot_features
            other = client_module.RobotClient(_client_config(port, tmp_path / "b", env="avoiding"))
            assert not other.start()
            assert service.policy is policy and service.lerobot_features is features
            assert client_hooks.FAILURES[0].startswith(f"{CLIENT_REFUSED}: the robot client does not give what the "
                                                       "PDP policy needs: 'observation.state' has shape (4,)")
        finally:
            served.stop()


def test_a_policy_the_server_cannot_load_is_named_by_the_client(server_module, client_module, tmp_path):
    """A load that fails on the server (here a --policy.steer_mode the checkpoint has no mode of) ends the client at
    connect naming the error, not with "no server listening, or it refused the policy"."""
    from lerobot_pdp.policy_server import CLIENT_REFUSED

    with _serving(server_module, ["--steer_mode=99"]) as (_, port, _, _):
        client = client_module.RobotClient(_client_config(port, tmp_path))
        assert not client.start()
    assert client_hooks.FAILURES[0].startswith(f"{CLIENT_REFUSED}: loading ")
    assert "failed (KeyError: steer_mode 99 is not a mode of this checkpoint" in client_hooks.FAILURES[0]


def test_a_chunk_that_arrives_before_the_must_go_flag_is_cleared_does_not_stall_the_run(
        server_module, client_module, tmp_path):
    """LeRobot's control loop clears "must go" after sending a must-go observation; the chunk answering it can
    arrive first (a fast server) and its set would be undone, leaving every later observation filterable as
    too similar. Forced here: the send returns only once the real server's chunk has reached the receiver."""
    with _serving(server_module) as (_, port, _, _):
        client = client_module.RobotClient(_client_config(port, tmp_path))
        assert client.start()
        receiver = threading.Thread(target=client.receive_actions, daemon=True)
        receiver.start()
        client.start_barrier.wait()  # the control loop's side of LeRobot's start barrier
        send = client.stub.SendObservations

        def send_then_wait_for_the_chunk(*args, **kwargs):
            reply = send(*args, **kwargs)
            deadline = time.monotonic() + 60
            while client._pdp_chunks == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            return reply

        client.stub.SendObservations = send_then_wait_for_the_chunk
        try:
            assert client.must_go.is_set() and not client.actions_available()
            client.control_loop_observation("")  # a must-go observation; its chunk arrives before the clear
            assert client._pdp_chunks == 1 and client.actions_available()
            assert client.must_go.is_set()  # LeRobot's clear would leave it unset: the next empty queue stalls
        finally:
            client.stop()
            receiver.join(10)


def test_a_client_serving_pdp_that_blends_chunks_or_sends_from_an_empty_queue_only_is_warned(client_module, tmp_path,
                                                                                           caplog):
    """LeRobot's client blends a chunk's actions with those still queued from the last one by default (0.3 old +
    0.7 new): two samples of a multimodal policy averaged. With ``--chunk_size_threshold=0`` it sends observations
    only when its queue is empty: none of the frames before them, which PDP's history holds. A client serving
    PDP either way is told so, and the flag to use."""
    port = _free_port()  # the client only connects at start()
    with caplog.at_level("WARNING", logger=client_hooks.__name__):
        client_module.RobotClient(_client_config(port, tmp_path, aggregation="latest_only"))
        assert not caplog.records
        client_module.RobotClient(_client_config(port, tmp_path / "2", aggregation="weighted_average"))
        config = _client_config(port, tmp_path / "3")
        config.chunk_size_threshold = 0.0
        client_module.RobotClient(config)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and "blends the overlapping actions of two chunks (--aggregate_fn_name=weighted_average)" \
        in said[0] and said[0].endswith("pass --aggregate_fn_name=latest_only"), said
    assert said[1].startswith("--chunk_size_threshold=0.0: this client sends an observation only when its queue is "
                              "empty") and said[1].endswith("keep LeRobot's default 0.5"), said


def test_a_chunk_planned_before_the_scene_reset_is_dropped(client_module, tmp_path):
    """pdp_sim drops the client's queued actions when it resets its scene; a chunk still in flight then (planned
    from the ended episode's observation) arrives after it and would run at the next episode's start: dropped
    too, by its observation's time (PDP's server times the first action a control step after it)."""
    from lerobot.async_inference.helpers import TimedAction

    client = client_module.RobotClient(_client_config(_free_port(), tmp_path))
    dt = client.config.environment_dt

    def chunk(observed_at: float) -> list:
        return [TimedAction(timestamp=observed_at + (i + 1) * dt, timestep=5 + i, action=torch.zeros(2))
                for i in range(8)]

    planned_at = time.time()
    client._aggregate_action_queues(chunk(planned_at), client.config.aggregate_fn)
    assert client.action_queue.qsize() == 8
    client.robot._engine.reset()  # the scene reset: a new episode
    assert client.action_queue.qsize() == 0
    client._aggregate_action_queues(chunk(planned_at), client.config.aggregate_fn)  # in flight at the reset
    assert client.action_queue.qsize() == 0
    client._aggregate_action_queues(chunk(time.time()), client.config.aggregate_fn)  # the new episode's
    assert client.action_queue.qsize() == 8 and client._pdp_chunks == 3


def test_a_scene_reset_waits_for_a_chunk_being_checked_and_queued(client_module, tmp_path):
    """The receiver checks a chunk against the last scene reset, then LeRobot queues it; a reset on the control
    thread between the two would clear the queue and then get the ended episode's chunk: it waits instead, and
    drops the chunk with the rest."""
    import threading

    from lerobot.async_inference.helpers import TimedAction

    client = client_module.RobotClient(_client_config(_free_port(), tmp_path))
    dt = client.config.environment_dt
    checked, check = threading.Event(), client._planned_before_reset

    def preempted_after_the_check(first):
        planned_before = check(first)
        checked.set()
        time.sleep(0.2)  # the receiver loses the core right after its check
        return planned_before

    client._planned_before_reset = preempted_after_the_check
    old = [TimedAction(timestamp=time.time() + (i + 1) * dt, timestep=5 + i, action=torch.zeros(2)) for i in range(8)]
    receiver = threading.Thread(target=client._aggregate_action_queues, args=(old, client.config.aggregate_fn))
    receiver.start()
    assert checked.wait(5)
    client.robot._engine.reset()  # the control thread: a new episode
    receiver.join(5)
    assert client.action_queue.qsize() == 0


def test_a_client_that_cannot_reach_a_server_exits_with_status_1(client_module, tmp_path):
    """LeRobot's entry point returns (status 0) when the client could not start; with pdp_sim it exits 1 and
    says why."""
    config = _client_config(_free_port(), tmp_path)  # nothing listens there
    with pytest.raises(SystemExit) as ended:
        client_module.async_client(config)
    assert "could not start with the policy server at 127.0.0.1:" in str(ended.value.code)
    assert not _outcomes(tmp_path / "outcomes.jsonl")


def _client_running(client_module, config, seen: list) -> tuple[threading.Thread, list]:
    """LeRobot's ``async_client`` entry point in a thread, once the server has passed three of its observations to
    the policy: (the thread, the exit codes it raised, filled when it ends)."""
    ended: list = []

    def run():
        try:
            client_module.async_client(config)
        except SystemExit as e:
            ended.append(e.code)

    main = threading.Thread(target=run, daemon=True)
    main.start()
    deadline = time.monotonic() + 120
    while len(seen) < 3 and time.monotonic() < deadline and main.is_alive():
        time.sleep(0.05)
    assert len(seen) >= 3, "the run never reached the server"
    return main, ended


def test_a_server_lost_mid_run_ends_the_run_with_status_1(server_module, client_module, tmp_path, monkeypatch):
    """LeRobot's client keeps sending to a server that is gone, for ever; a pdp_sim run ends once no
    observation has reached it for ``SERVER_LOST_S``, and the entry point exits 1 naming it."""
    monkeypatch.setattr(client_hooks, "SERVER_LOST_S", 1.0)
    with _serving(server_module) as (_, port, seen, grpc_server):
        main, ended = _client_running(client_module, _client_config(port, tmp_path, episodes=50), seen)
        grpc_server.stop(0)
        main.join(60)
    assert not main.is_alive(), "the run did not end after its server was lost"
    assert ended and "lost the policy server at 127.0.0.1:" in str(ended[0]), ended


def test_a_chunk_the_server_cannot_plan_ends_the_run_with_status_1(server_module, client_module, tmp_path):
    """LeRobot's server logs a chunk it could not plan and answers nothing, and its client asks again for good (a
    robot waiting for actions that never come). Served PDP's action request fails with the error instead, the
    server serves nothing more, and the client ends its run and exits 1 naming it. The fault: a weight of the
    served denoiser turned NaN mid-run, which PDP's guard refuses to act on."""
    with _serving(server_module) as (service, port, seen, _):
        main, ended = _client_running(client_module, _client_config(port, tmp_path, episodes=50), seen)
        weight = dict(service.policy.model.named_parameters())["denoiser.final.1.weight"]
        with torch.no_grad():
            weight.fill_(float("nan"))
        main.join(60)
        assert not main.is_alive(), "the run did not end after the server failed to plan"
        assert not service.running  # nothing more is served until a client connects again
    assert ended and str(ended[0]).startswith("robot client: the PDP policy server could not plan a chunk from "
                                              "observation #"), ended
    assert "FloatingPointError: PDP generated non-finite actions" in str(ended[0]), ended
    assert len(_outcomes(tmp_path / "outcomes.jsonl")) < 50


# ------------------------------------------------------------------------------------------------ real processes


@pytest.mark.slow
def test_record_then_serve_a_fitted_pdp_to_lerobot_robot_client(reach_around_pdp, tmp_path):
    """``lerobot-record`` one demonstration of reach-around's validation scene val3, serve PDP fitted to it at load
    (``--policy.steer_dataset_root``, z and chunk noises), and let LeRobot's robot client drive pdp_sim in that scene:
    the bar of the synchronous rollout test (3 of 5 episodes reach the goal; the training modes collide with val3's
    wall)."""
    import socket

    from conftest import run_cli
    from test_robot_loop import CLI_ENV, _record

    env = {**CLI_ENV, "HF_LEROBOT_HOME": str(tmp_path / "home")}
    demo, outcomes = tmp_path / "demo", tmp_path / "outcomes.jsonl"
    run_cli(_record(tmp_path, demo, 1, "--robot.scene=val3", "--teleop.waypoints=scene", "--teleop.seed=1"),
            timeout=300, env=env)
    port = _free_port()
    full_env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", **env}
    server_log, client_log = tmp_path / "server.log", tmp_path / "client.log"
    with server_log.open("w") as out:
        served = subprocess.Popen([sys.executable, "-m", "lerobot_pdp.policy_server", "--host=127.0.0.1",
                                   f"--port={port}", "--fps=50", f"--policy.steer_dataset_root={demo}",
                                   "--policy.steer_episode_index=0", "--policy.fit_noise=chunks"], stdout=out, stderr=subprocess.STDOUT, env=full_env,
                                  cwd=tmp_path)  # LeRobot's log files go under ./logs
    try:
        deadline = time.monotonic() + 120
        while True:  # the client gives up at once when no server listens yet (the fit runs when it connects)
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert served.poll() is None and time.monotonic() < deadline, server_log.read_text()[-3000:]
                time.sleep(0.5)
        with client_log.open("w") as out:
            client = subprocess.Popen(
                [sys.executable, "-m", "lerobot.async_inference.robot_client", "--robot.type=pdp_sim",
                 "--robot.env=reach-around", "--robot.scene=val3", "--robot.episodes=5", f"--robot.outcomes={outcomes}",
                 f"--robot.calibration_dir={tmp_path / 'cal'}", f"--server_address=127.0.0.1:{port}",
                 "--policy_type=pdp", f"--pretrained_name_or_path={reach_around_pdp}", "--policy_device=cpu",
                 "--actions_per_chunk=8", "--fps=50", "--aggregate_fn_name=latest_only", "--task=reach the goal"],
                stdout=out, stderr=subprocess.STDOUT, env=full_env, cwd=tmp_path)
        try:
            code = client.wait(timeout=420)
        except subprocess.TimeoutExpired:
            client.kill()
            code = "killed after 420 s"
    finally:
        served.terminate()
        served.wait(timeout=30)
    logs = (f"client ({code}): {client_log.read_text()[-4000:]}\nserver: {server_log.read_text()[-4000:]}\n"
            f"outcomes: {_outcomes(outcomes)}")
    lines = _outcomes(outcomes)
    assert code == 0 and len(lines) == 5, logs
    assert "Error receiving actions" not in client_log.read_text(), logs  # the run ended cleanly
    server_log = server_log.read_text()
    assert re.search(r"fitted latent and \d+ chunk noise\(s\) to", server_log), server_log[-3000:]
    print(f"val3 served: {sum(d['success'] for d in lines)} of {len(lines)} episodes reached the goal")
    assert sum(d["success"] for d in lines) >= 3, lines


def test_sigterm_unwinds_the_client_or_server_as_ctrl_c_does(capsys):
    """LeRobot's robot client and policy server handle neither signal: SIGTERM killed the client on the spot (no
    robot disconnected, no outcome line) and Ctrl-C printed a KeyboardInterrupt traceback. Under PDP both unwind
    through the program's finally blocks and end with one line and the signal's status."""
    import os
    import signal

    from lerobot_pdp.cli_errors import ending_on_signals

    before, cleaned = signal.getsignal(signal.SIGTERM), []
    with pytest.raises(SystemExit) as ended, ending_on_signals("robot client"):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(10)
        finally:
            cleaned.append("robot disconnected")
    assert ended.value.code == 143 and cleaned == ["robot disconnected"]
    assert capsys.readouterr().err == "robot client: stopped by SIGTERM\n"
    assert signal.getsignal(signal.SIGTERM) is before
    with pytest.raises(SystemExit) as ended, ending_on_signals("lerobot_pdp.policy_server"):
        raise KeyboardInterrupt  # Ctrl-C
    assert ended.value.code == 130 and capsys.readouterr().err == "lerobot_pdp.policy_server: stopped by SIGINT\n"
