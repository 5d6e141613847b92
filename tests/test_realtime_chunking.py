"""PDP under LeRobot's real-time chunking engine (``lerobot-rollout --inference.type=rtc``): the call shape the
engine checks, the prefix imposed on a new chunk, the engine's zero padding, what is refused."""

import logging
import threading

import numpy as np
import pytest
import torch
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.rollout.inference.rtc import supports_rtc_inference
from policies import saved_steerable_checkpoint, small_policy


@pytest.fixture(autouse=True)
def _lerobots_queue_back(monkeypatch):
    """init_rtc_processor gives LeRobot's loaded RTC engine PDP's queue class; each test leaves LeRobot's."""
    import lerobot.rollout.inference.rtc as engine

    monkeypatch.setattr(engine, "ActionQueue", engine.ActionQueue)
    monkeypatch.setattr(engine.RTCInferenceEngine, "notify_observation", engine.RTCInferenceEngine.notify_observation)


OBS = {"observation.state": torch.tensor([[0.3, -0.2]]), "observation.environment_state": torch.tensor([[0.1, 0.4]])}


def _rtc_policy(meta, horizon: int = 5, enabled: bool = True, seed: int = 0):
    torch.manual_seed(seed)  # the weights
    p = small_policy(meta)
    p.eval()
    p.set_latent(p.mode_latents()[1])  # not a latent drawn per episode
    p.config.rtc_config = RTCConfig(execution_horizon=horizon, enabled=enabled)  # what lerobot-rollout sets
    p.init_rtc_processor()
    return p


def _noise(p, seed: int = 0):
    return torch.randn(1, p.config.horizon, p.action_dim, generator=torch.Generator().manual_seed(seed))


def test_lerobot_accepts_pdp_for_its_rtc_engine_and_gets_the_whole_predicted_future(synthetic_meta):
    p = _rtc_policy(synthetic_meta)
    assert supports_rtc_inference(p)  # LeRobot's own check: supports_rtc() and the call's keywords
    chunk = p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None)
    cfg = p.config
    assert chunk.shape == (1, cfg.horizon - cfg.n_obs_steps + 1, p.action_dim)
    history = {k: v[:, None].expand(-1, cfg.n_obs_steps, -1) for k, v in OBS.items()}
    noise = _noise(p)
    # one observation = a history of copies of it; without a prefix, the plain sampler's chunk
    one = p.predict_action_chunk(OBS, noise=noise, inference_delay=0, prev_chunk_left_over=None)
    torch.testing.assert_close(one, p.predict_action_chunk(history, noise=noise, inference_delay=0,
                                                           prev_chunk_left_over=None))
    plain = p.generate(p.model.obs_cond(history), p.current_latent(1), noise=noise)
    torch.testing.assert_close(one, plain[:, cfg.n_obs_steps - 1 :])


def test_a_new_chunk_continues_the_unexecuted_actions_over_the_delay_and_fades_to_free(synthetic_meta):
    p = _rtc_policy(synthetic_meta, horizon=6)
    b, delay = 32, 2
    obs = {k: v.expand(b, -1) for k, v in OBS.items()}
    noise = torch.randn(b, p.config.horizon, p.action_dim, generator=torch.Generator().manual_seed(0))
    prefix = p.predict_action_chunk(OBS, noise=_noise(p, 1), inference_delay=0, prev_chunk_left_over=None)[0, :6]
    free = p.predict_action_chunk(obs, noise=noise, inference_delay=delay, prev_chunk_left_over=None)
    guided = p.predict_action_chunk(obs, noise=noise, inference_delay=delay, prev_chunk_left_over=prefix)
    # weight 1 over the delay: exactly the actions the robot executes while the chunk is generated
    torch.testing.assert_close(guided[:, :delay], prefix[:delay].expand(b, -1, -1))
    # decaying weights up to the execution horizon: closer to the prefix than free chunks, on average
    gap_guided = (guided[:, delay:6] - prefix[delay:6]).norm(dim=-1).mean()
    gap_free = (free[:, delay:6] - prefix[delay:6]).norm(dim=-1).mean()
    assert gap_guided < 0.85 * gap_free
    assert torch.isfinite(guided).all()


def test_the_engines_zero_padding_is_not_taken_for_actions(synthetic_meta):
    """LeRobot pads a short leftover with zero rows up to execution_horizon: those rows impose nothing."""
    p = _rtc_policy(synthetic_meta, horizon=6)
    noise = _noise(p)
    prefix = p.predict_action_chunk(OBS, noise=_noise(p, 1), inference_delay=0, prev_chunk_left_over=None)[0, :3]
    padded = torch.cat([prefix, torch.zeros(3, p.action_dim)])
    short = p.predict_action_chunk(OBS, noise=noise, inference_delay=1, prev_chunk_left_over=prefix)
    torch.testing.assert_close(p.predict_action_chunk(OBS, noise=noise, inference_delay=1,
                                                      prev_chunk_left_over=padded), short)
    nothing = p.predict_action_chunk(OBS, noise=noise, inference_delay=1, prev_chunk_left_over=torch.zeros(6, 2))
    torch.testing.assert_close(nothing, p.predict_action_chunk(OBS, noise=noise, inference_delay=1,
                                                               prev_chunk_left_over=None))


def test_rtc_disabled_appends_chunks_without_a_prefix(synthetic_meta, caplog):
    """``--inference.rtc.enabled=false``: the engine appends chunks to its queue; nothing is imposed (and the
    start-up line says so, not that chunks are held)."""
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.realtime_chunking"):
        p = _rtc_policy(synthetic_meta, enabled=False)
    assert "appended, nothing held to the last one" in caplog.text and "holds each new chunk" not in caplog.text
    noise = _noise(p)
    prefix = torch.ones(5, p.action_dim) * 0.5
    torch.testing.assert_close(
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=prefix),
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=None))


def test_execution_horizon_0_holds_nothing(synthetic_meta):
    """``--inference.rtc.execution_horizon=0``: the engine cuts the left-over to no rows; the chunk is free (the
    queue still replaces its actions)."""
    p = _rtc_policy(synthetic_meta, horizon=0)
    noise = _noise(p)
    torch.testing.assert_close(
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=torch.ones(0, p.action_dim)),
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=None))


def test_steering_the_engine_cannot_follow_is_refused_with_the_way_out(synthetic_meta):
    p = _rtc_policy(synthetic_meta)
    p.config.segment_gripper_dim = 0  # a stand-in gripper: the policy has phases
    means = p.mode_latents()
    p.set_latent(torch.stack([means[0], means[1]]))  # one latent per phase
    p.init_rtc_processor()  # PDP's queue reports the executed gripper commands: phases follow
    p.config.rtc_consumed_delay = False  # LeRobot's queue: nothing reports them
    with pytest.raises(ValueError, match=r"one latent per phase \(2 phases\).*rtc_consumed_delay=true.*"
                                         r"--inference.type=sync"):
        p.init_rtc_processor()
    with pytest.raises(ValueError, match="--inference.type=sync"):
        p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None)
    p.steering.activate(means[0], noise=torch.zeros(3, p.config.horizon, p.action_dim))
    with pytest.raises(ValueError, match=r"3 fitted chunk noises.*fit_noise=none"):
        p.init_rtc_processor()
    p.set_latent(means[2])  # one latent: fine
    p.init_rtc_processor()
    assert p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None).shape[1] > 0
    with pytest.raises(KeyError, match="observation.environment_state"):
        p.predict_action_chunk({"observation.state": OBS["observation.state"]}, inference_delay=0,
                               prev_chunk_left_over=None)


def test_a_chunk_generated_across_a_reset_is_dropped(synthetic_meta):
    """The engine's thread may be generating when the robot starts a new episode (``reset()``): that chunk
    answers the last episode's observation, so it comes back empty and the engine's queue stays empty."""
    p = _rtc_policy(synthetic_meta)
    generate = p.model.generate

    def reset_meanwhile(*args, **kwargs):
        p.reset()  # what the control thread does while the engine's thread samples
        return generate(*args, **kwargs)

    p.model.generate = reset_meanwhile
    assert p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None).shape == (1, 0, p.action_dim)
    p.model.generate = generate
    assert p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None).shape[1] > 0


def _loop_step(q) -> float:
    """One step of lerobot-rollout's loop: publish an observation, then execute the step's action."""
    q.observed()
    return float(q.get()[0])


@pytest.mark.parametrize("read_before_the_steps_action", [False, True])
def test_a_new_chunk_continues_from_its_observations_step(read_before_the_steps_action):
    """The chunk from the observation of step 1 plans steps 1, 2, ...: after two more steps executed while it was
    generated, the robot's next action (step 4) is its fourth, whether the engine read that observation before or
    (as usual) after the loop executed step 1's action; its prefix starts at step 1's action."""
    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    q = ConsumedDelayQueue(RTCConfig())
    first, new = torch.arange(10.0)[:, None], 100 + torch.arange(15.0)[:, None]  # action i: step i; new j: 1 + j
    q.merge(first, first, 0)
    assert _loop_step(q) == 0.0
    q.observed()  # step 1's observation
    if not read_before_the_steps_action:
        assert float(q.get()[0]) == 1.0
    index, prefix = q.get_action_index(), q.get_left_over()  # the engine starts a chunk from that observation
    if read_before_the_steps_action:
        assert float(q.get()[0]) == 1.0
    assert prefix[:, 0].tolist() == list(range(1, 10))
    assert [_loop_step(q), _loop_step(q)] == [2.0, 3.0]  # executed while the chunk was generated
    q.merge(new, new, 2, index)
    assert float(q.get()[0]) == 103.0  # step 4


def test_a_chunk_started_before_a_new_episode_is_not_merged_into_it():
    """LeRobot's engine merges a chunk after PDP returned it, and its reset() at a new episode (pdp_sim, the
    episodic strategy) does not wait for the engine's thread: a chunk started from the ended episode's observation
    and merged after the reset is dropped, not executed at the new episode's start; one started after it is merged."""
    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    q = ConsumedDelayQueue(RTCConfig())
    old, new = torch.zeros(8, 1), torch.ones(8, 1)
    index = q.get_action_index()  # the engine starts a chunk in the episode that ends
    q.clear()  # engine.reset(): a new episode
    q.merge(old, old, 0, index)
    assert q.qsize() == 0
    index = q.get_action_index()
    q.merge(new, new, 0, index)
    assert q.qsize() == 8 and float(q.get()[0]) == 1.0


def test_with_fitted_noises_the_engine_replans_at_their_steps_only():
    """Fitted chunk noise j belongs to the demonstration's frames from j * n_action_steps: while noises are replayed,
    the queue lets the engine start a chunk only at the observations of steps 0, 8, 16, ..., once each, whatever
    its threshold (LeRobot's default 30 replans back to back without noises). A queue run dry lets it replan at
    once."""
    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    threshold, noises, step = 30, [True], [0]
    q = ConsumedDelayQueue(RTCConfig())
    q.noise_cadence = lambda: (step[0], 8 if noises[0] else None)
    q.on_executed = lambda action: step.__setitem__(0, step[0] + 1)  # the episode's executed steps, as PDP counts
    chunk = torch.arange(15.0)[:, None]  # what PDP returns: horizon - n_obs_steps + 1 actions

    def run(steps: int) -> list[int]:
        """lerobot-rollout's loop with the engine's thread: each step publishes its observation, the engine may
        start a chunk from it, the step's action is executed, and the chunk lands two actions later (a chunk's
        generation spans about two steps at 50 fps)."""
        planned, pending = [], None
        for _ in range(steps):
            q.observed()
            if pending is None and q.qsize() <= threshold:
                pending = q.get_action_index()
                planned.append(step[0])
            q.get()
            if pending is not None and step[0] - planned[-1] == 2:
                q.merge(chunk, chunk, 2, pending)
                pending = None
        return planned

    q.observed()
    assert q.qsize() == 0  # the episode's first chunk: an empty queue
    q.merge(chunk, chunk, 0, q.get_action_index())
    assert run(41) == [8, 16, 24, 32, 40]
    noises[0] = False  # LeRobot's threshold alone: a new chunk as soon as the last one landed
    assert np.diff(run(12)).tolist() == [2] * 5
    noises[0] = True
    q.clear()  # a new episode: the queue is empty, a chunk is started whatever the step
    step[0] = 3
    q.observed()
    assert q.qsize() == 0


def test_the_prefix_reaches_into_the_chunk_before_when_a_new_chunk_landed_after_the_observation():
    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    q = ConsumedDelayQueue(RTCConfig())
    q.merge(torch.arange(3.0)[:, None], torch.arange(3.0)[:, None], 0)
    q.observed()
    assert float(q.get()[0]) == 0.0  # step 0's action, from the first chunk
    q.merge(10 + torch.arange(5.0)[:, None], 10 + torch.arange(5.0)[:, None], 0)  # replanned meanwhile (step 1 on)
    q.get_action_index()  # a chunk from step 0's observation
    assert q.get_left_over()[:, 0].tolist() == [0.0, 10.0, 11.0, 12.0, 13.0, 14.0]


def test_lerobots_queue_rule_misaligns_a_new_chunk():
    """LeRobot's queue drops ceil(latency * fps) actions and takes the prefix from the engine's read: with the
    usual read (after the step's action), the prefix starts one step late."""
    from lerobot.policies.rtc.action_queue import ActionQueue

    q = ActionQueue(RTCConfig())
    q.merge(torch.arange(10.0)[:, None], torch.arange(10.0)[:, None], 0)
    q.get(), q.get()  # steps 0 and 1; the engine then reads step 1's observation
    assert float(q.get_left_over()[0, 0]) == 2.0


def test_the_engine_announces_observations_to_pdps_queue(synthetic_meta):
    import lerobot.rollout.inference.rtc as engine

    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    p = small_policy(synthetic_meta)
    p.config.rtc_config = RTCConfig()
    p.init_rtc_processor()
    e = engine.RTCInferenceEngine.__new__(engine.RTCInferenceEngine)  # the two attributes notify_observation uses
    e._obs_lock, e._obs_holder = threading.Lock(), {}
    e._action_queue = q = ConsumedDelayQueue(RTCConfig())
    q.merge(torch.zeros(4, 1), torch.zeros(4, 1), 0)
    q.get()
    e.notify_observation({"x": 1})
    assert q.executed_at_observation == 1 and e._obs_holder["obs"] == {"x": 1}


def test_per_phase_latents_advance_on_the_actions_the_rtc_loop_executes(synthetic_meta):
    """Under RTC the engine replans at its own pace; PDP's queue tells the policy each action the loop takes from
    it, so a gripper flip held for ``phase_switch_steps`` actions moves the next chunk to the next phase's latent,
    and a new episode starts at the first phase again."""

    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    p = _rtc_policy(synthetic_meta)
    p.config.segment_gripper_dim = 0  # a stand-in gripper: normalised x above the threshold's value = closed
    means = p.mode_latents()
    phases = torch.stack([means[0], means[2]])
    p.set_latent(phases)
    p.init_rtc_processor()
    e = _engine_for(p, synthetic_meta)
    e._action_queue = q = ConsumedDelayQueue(RTCConfig())
    closed = p.stats.normalized_value("action", 0, p.config.segment_gripper_threshold)
    steps = p.config.phase_switch_steps
    gripper = [closed - 1.0] * 3 + [closed + 1.0] * (steps + 2)  # open, then closed and held
    chunk = torch.tensor([[g] + [0.0] * (p.action_dim - 1) for g in gripper])
    q.merge(chunk, chunk, 0)
    for k in range(len(gripper)):
        e.notify_observation(_raw(k))  # the loop publishes, then executes that step's action
        assert q.get() is not None
        phase = int(p.steering.phases.phases(1, "cpu")[0])
        assert phase == (1 if k >= 3 + steps - 1 else 0), (k, phase)
    torch.testing.assert_close(p.current_latent(1), phases[1][None])  # the engine's next chunk: the carry latent
    assert p.predict_action_chunk(_preprocessed(e, _raw(len(gripper) - 1)), inference_delay=0,
                                  prev_chunk_left_over=None).shape[1] > 0
    p.reset()  # a new episode
    torch.testing.assert_close(p.current_latent(1), phases[0][None])


def test_fitted_chunk_noises_follow_the_episodes_step_under_rtc(synthetic_meta):
    """Noise j is fitted to the demonstration's frames from ``j * n_action_steps``: under RTC a chunk planned at the
    episode's step k (the actions the loop executed, reported by PDP's queue) starts from noise k // n_action_steps,
    however often the engine replans; a new episode starts at noise 0."""
    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    p = _rtc_policy(synthetic_meta)
    n = p.config.n_action_steps
    noises = torch.stack([torch.full((p.config.horizon, p.action_dim), float(j)) for j in range(3)])
    p.steering.activate(p.mode_latents()[1], noise=noises)
    p.init_rtc_processor()  # PDP's queue reports the executed actions: the noises are accepted
    e = _engine_for(p, synthetic_meta)
    e._action_queue = q = ConsumedDelayQueue(RTCConfig())
    used = []
    generate = p.model.generate
    p.model.generate = lambda obs, z, noise=None, **k: (used.append(noise[0, 0, 0].item()), generate(obs, z, noise, **k))[1]
    actions = torch.zeros(6 * n, p.action_dim)
    q.merge(actions, actions, 0)
    step = 0
    for executed in (0, 2, n - 2, 1, n, 3 * n):  # the engine replans after this many more executed actions
        for _ in range(executed):
            e.notify_observation(_raw(step))
            assert q.get() is not None
            step += 1
        p.predict_action_chunk(_preprocessed(e, _raw(step)), inference_delay=0, prev_chunk_left_over=None)
    assert used == [0.0, 0.0, 1.0, 1.0, 2.0, 2.0]  # steps 0, 2, n, n + 1, 2n + 1, 5n + 1 (the last noise repeats)
    p.reset()  # a new episode
    p.predict_action_chunk(_preprocessed(e, _raw(step)), inference_delay=0, prev_chunk_left_over=None)
    assert used[-1] == 0.0


def _engine_for(policy, meta):
    """LeRobot's RTC engine with what its thread uses to turn a raw observation into the policy's input."""
    import types

    import lerobot.rollout.inference.rtc as engine
    from lerobot.policies.factory import make_pre_post_processors

    e = engine.RTCInferenceEngine.__new__(engine.RTCInferenceEngine)
    e._obs_lock, e._obs_holder, e._action_queue, e._policy = threading.Lock(), {}, None, policy
    e._hw_features = {k: {"dtype": "float32", "shape": ft.shape, "names": [f"{k}.{i}" for i in range(ft.shape[0])]}
                      if len(ft.shape) == 1 else {"dtype": "image", "shape": (*ft.shape[1:], ft.shape[0]), "names": None}
                      for k, ft in policy.config.condition_features.items()}
    e._device, e._task, e._robot = "cpu", "", types.SimpleNamespace(robot_type="test")
    e._preprocessor, _ = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    return e


def _raw(k: int) -> dict:
    return {f"{key}.{i}": 0.1 * k + 0.05 * i + j for j, key in enumerate(OBS) for i in range(2)}


def _preprocessed(e, obs: dict) -> dict:
    from lerobot_pdp.realtime_chunking import _preprocess

    return {k: v for k, v in _preprocess(e, obs).items() if k in e._policy.config.condition_features}


def test_a_chunk_is_conditioned_on_the_observations_the_loop_published_up_to_its_own(synthetic_meta, caplog):
    """The engine passes one observation; PDP conditions on it and the one the loop published before it, as
    select_action would, even when the loop published another while the chunk started; a chunk from an observation
    read before a reset is dropped; the new episode's first chunk repeats its observation, as at select_action's
    first chunk."""
    p = _rtc_policy(synthetic_meta)
    assert p.config.n_obs_steps == 2
    e = _engine_for(p, synthetic_meta)
    for k in range(3):
        e.notify_observation(_raw(k))  # PDP's announcing notify_observation, installed by init_rtc_processor
    current, before = _preprocessed(e, _raw(1)), _preprocessed(e, _raw(0))  # the chunk's is not the latest
    history = {k: torch.stack([before[k], current[k]], dim=1) for k in OBS}
    noise = _noise(p)
    got = p.predict_action_chunk(current, noise=noise, inference_delay=0, prev_chunk_left_over=None)
    torch.testing.assert_close(got, p.predict_action_chunk(history, noise=noise, inference_delay=0,
                                                           prev_chunk_left_over=None))
    repeated = p.predict_action_chunk({k: torch.stack([current[k]] * 2, dim=1) for k in OBS}, noise=noise,
                                      inference_delay=0, prev_chunk_left_over=None)
    assert not torch.allclose(got, repeated)
    p.reset()  # a new episode: the frames published before it are not its history
    stale = p.predict_action_chunk(current, inference_delay=0, prev_chunk_left_over=None)  # read before the reset
    assert stale.shape == (1, 0, p.action_dim)  # no action of the episode that ended reaches the new one
    e.notify_observation(_raw(5))
    first = _preprocessed(e, _raw(5))
    torch.testing.assert_close(p.predict_action_chunk(first, noise=noise, inference_delay=0, prev_chunk_left_over=None),
                               p.predict_action_chunk({k: torch.stack([first[k]] * 2, dim=1) for k in OBS},
                                                      noise=noise, inference_delay=0, prev_chunk_left_over=None))
    with caplog.at_level("WARNING"):  # an observation not among those published: repeated, and said once
        for _ in range(2):
            p.predict_action_chunk(_preprocessed(e, _raw(9)), inference_delay=0, prev_chunk_left_over=None)
    assert p._rtc_observations.unmatched == 2 and caplog.text.count("was not among the last") == 1
    p.config.rtc_observation_history = False
    p.init_rtc_processor()
    e.notify_observation(_raw(6))
    e.notify_observation(_raw(7))
    last = _preprocessed(e, _raw(7))  # without the history: the chunk's observation repeated
    torch.testing.assert_close(p.predict_action_chunk(last, noise=noise, inference_delay=0, prev_chunk_left_over=None),
                               p.predict_action_chunk({k: torch.stack([last[k]] * 2, dim=1) for k in OBS},
                                                      noise=noise, inference_delay=0, prev_chunk_left_over=None))
    p.reset()  # ... and a chunk read before a reset is still told apart
    assert p.predict_action_chunk(last, inference_delay=0, prev_chunk_left_over=None).shape == (1, 0, p.action_dim)


def test_a_robot_at_rest_is_told_apart_by_its_camera(tmp_path):
    """Two published frames with equal vectors (a robot at rest) and different images: the chunk's own is found
    by its image, so its history is the frame before it, not its successor."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_pdp import PDPPolicy

    ckpt, data = saved_steerable_checkpoint(tmp_path, camera="top")
    p = PDPPolicy.from_pretrained(ckpt)
    p.config.rtc_config = RTCConfig(execution_horizon=3)
    p.init_rtc_processor()
    e = _engine_for(p, LeRobotDatasetMetadata("local/ra", root=data))
    vectors = [k for k, ft in e._hw_features.items() if ft["dtype"] == "float32"]

    def frame(k: int, image_seed: int) -> dict:
        values = {name: 0.1 * k + 0.01 * i for key in vectors for i, name in enumerate(e._hw_features[key]["names"])}
        image = np.random.default_rng(image_seed).integers(0, 255, e._hw_features["observation.images.top"]["shape"])
        return {**values, "top": image.astype(np.uint8)}

    frames = [frame(0, 0), frame(1, 1), frame(1, 2)]  # the last two: at rest, the camera sees a change
    for f in frames:
        e.notify_observation(f)
    batch = _preprocessed(e, frames[1])
    history, ended = p._rtc_observations.history(p, batch)
    assert not ended
    earlier = _preprocessed(e, frames[0])
    for k in p.config.condition_features:
        torch.testing.assert_close(history[k], torch.stack([earlier[k], batch[k]], dim=1))
    assert p._rtc_observations.matched == 1


def test_prepare_rtc_gives_lerobots_engine_the_consumed_delay_queue_unless_told_not_to(synthetic_meta, monkeypatch,
                                                                                       caplog):
    import lerobot.rollout.inference.rtc as engine
    from lerobot.policies.rtc.action_queue import ActionQueue

    from lerobot_pdp.realtime_chunking import ConsumedDelayQueue

    monkeypatch.setattr(engine, "ActionQueue", ActionQueue)  # undone after the test
    p = small_policy(synthetic_meta, rtc_consumed_delay=False)
    p.config.rtc_config = RTCConfig()
    with caplog.at_level("INFO", logger="lerobot_pdp.realtime_chunking"):
        p.init_rtc_processor()
    assert engine.ActionQueue is ActionQueue
    assert "over its first 10 actions" in caplog.text  # the prefix advice, whichever queue
    caplog.clear()
    p.config.rtc_consumed_delay = True
    p.config.rtc_config = RTCConfig(execution_horizon=10)
    with caplog.at_level("INFO", logger="lerobot_pdp.realtime_chunking"):
        p.init_rtc_processor()
    assert engine.ActionQueue is ConsumedDelayQueue
    # the info line names the settings chosen on validation for this chunk size, and the run's own prefix length
    assert "--inference.queue_threshold=7 " in caplog.text and "over its first 10 actions" in caplog.text
    assert "3 is recommended" in caplog.text
    assert "conditioned on the last 2 observations the loop published" in caplog.text


def test_a_live_request_the_engine_cannot_follow_is_refused_and_the_latent_kept(synthetic_meta, tmp_path, caplog):
    """Under RTC a steering file asking for one latent per phase is refused like a bad request: logged, the robot
    acting on its current latent; a request it can follow still applies."""
    import json

    steer = tmp_path / "steer.json"
    steer.write_text(json.dumps({"mode": 1}))
    torch.manual_seed(0)
    p = small_policy(synthetic_meta, steer_file=str(steer), rtc_consumed_delay=False)  # nothing reports executed actions
    p.eval()
    p.config.segment_gripper_dim = 0  # a stand-in gripper: the policy has phases
    p.config.rtc_config = RTCConfig()
    p.init_rtc_processor()
    means = p.mode_latents()
    p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None)
    torch.testing.assert_close(p.active_latent, means[1][None])
    steer.write_text(json.dumps({"latent": [means[2].tolist(), means[3].tolist()]}))
    with caplog.at_level("ERROR"):
        chunk = p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None)
    assert chunk.shape[1] > 0 and "one latent per phase" in caplog.text and "keeping the current latent" in caplog.text
    torch.testing.assert_close(p.active_latent, means[1][None])
    steer.write_text(json.dumps({"mode": 3}))
    p.predict_action_chunk(OBS, inference_delay=0, prev_chunk_left_over=None)
    torch.testing.assert_close(p.active_latent, means[3][None])


def test_a_start_up_fit_of_chunk_noises_is_refused_under_rtc_before_fitting(synthetic_meta, monkeypatch):
    """lerobot-rollout loads (and so fits at start-up) before it tells the policy about RTC: on LeRobot's queue,
    which does not report the executed actions, chunk noises cannot be replayed in step and are refused from its
    command line before minutes of fitting (PDP's queue, the default, reports them: allowed)."""
    from lerobot_pdp.lerobot_command import rollout_with_rtc
    from lerobot_pdp.steering import refuse_paced_fit

    for argv, rtc in ((["/venv/bin/lerobot-rollout", "--inference.type=rtc"], True),
                      (["lerobot-rollout", "--inference.type", "rtc"], True),
                      (["lerobot-rollout", "--inference.type=sync"], False),
                      (["lerobot-eval", "--inference.type=rtc"], False)):
        monkeypatch.setattr("sys.argv", argv)
        assert rollout_with_rtc() is rtc, argv
    monkeypatch.setattr("sys.argv", ["lerobot-rollout", "--inference.type=rtc"])
    p = small_policy(synthetic_meta, steer_dataset_root=str(synthetic_meta.root), steer_episode_index=0,
                     fit_noise="chunks", fit_steps=10**6, rtc_consumed_delay=False)
    monkeypatch.setattr(p, "fit_latent", lambda *a, **k: pytest.fail("fitted before refusing"))
    with pytest.raises(ValueError, match=r"fit_noise=chunks .*with --policy.rtc_consumed_delay=false, the actions the "
                                         r"robot executes do not reach PDP.*Use --inference.type=sync, or "
                                         r"--policy.fit_noise=none"):
        p.apply_config_steering()
    assert not p.steering.active
    p.config.rtc_consumed_delay = True  # PDP's queue: the noises follow the executed actions
    refuse_paced_fit(p, (str(synthetic_meta.root), 0))  # not refused
