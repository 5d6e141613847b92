"""PDP under LeRobot's real-time chunking engine (``lerobot-rollout --inference.type=rtc``): the call shape the
engine checks, the prefix imposed on a new chunk, the engine's zero padding, what is refused."""

import pytest
import torch
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.rollout.inference.rtc import supports_rtc_inference
from policies import small_policy

OBS = {"observation.state": torch.tensor([[0.3, -0.2]]), "observation.environment_state": torch.tensor([[0.1, 0.4]])}


def _rtc_policy(meta, horizon: int = 5, enabled: bool = True):
    p = small_policy(meta)
    p.eval()
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
    noise, delay = _noise(p), 2
    prefix = p.predict_action_chunk(OBS, noise=_noise(p, 1), inference_delay=0, prev_chunk_left_over=None)[0, :6]
    free = p.predict_action_chunk(OBS, noise=noise, inference_delay=delay, prev_chunk_left_over=None)[0]
    guided = p.predict_action_chunk(OBS, noise=noise, inference_delay=delay, prev_chunk_left_over=prefix)[0]
    # weight 1 over the delay: exactly the actions the robot executes while the chunk is generated
    torch.testing.assert_close(guided[:delay], prefix[:delay])
    # decaying weights up to the execution horizon: closer to the prefix than the free chunk
    gap_guided = (guided[delay:6] - prefix[delay:6]).norm()
    gap_free = (free[delay:6] - prefix[delay:6]).norm()
    assert gap_guided < 0.8 * gap_free
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


def test_rtc_disabled_appends_chunks_without_a_prefix(synthetic_meta):
    """``--inference.rtc.enabled=false``: the engine appends chunks to its queue; nothing is imposed."""
    p = _rtc_policy(synthetic_meta, enabled=False)
    noise = _noise(p)
    prefix = torch.ones(5, p.action_dim) * 0.5
    torch.testing.assert_close(
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=prefix),
        p.predict_action_chunk(OBS, noise=noise, inference_delay=2, prev_chunk_left_over=None))


def test_steering_the_engine_cannot_follow_is_refused_with_the_way_out(synthetic_meta):
    p = _rtc_policy(synthetic_meta)
    means = p.mode_latents()
    p.set_latent(torch.stack([means[0], means[1]]))  # one latent per phase
    with pytest.raises(ValueError, match=r"one latent per phase \(2 phases\).*--inference.type=sync"):
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
