"""PDPConfig: registration, LeRobot contract, validation errors."""

import pytest
from lerobot.configs import PreTrainedConfig

from lerobot_pdp import PDPConfig


def test_registered_as_pdp():
    assert PreTrainedConfig.get_choice_class("pdp") is PDPConfig
    assert PDPConfig().type == "pdp"


def test_defaults_paper_where_not_chosen_on_validation():
    c = PDPConfig()
    assert (c.latent_dim, c.beta_kl, c.beta_geo, c.sdtw_gamma) == (2, 1e-3, 1.0, 1e-5)
    # the whole 20-step chain at inference: what validation kept (configuration_pdp.py)
    assert c.num_train_timesteps == c.num_inference_steps == 20
    assert c.optimizer_lr == c.embedding_lr == 1e-3  # chosen on validation (configuration_pdp.py)
    assert tuple(c.film_hidden_dims) == (16, 32)


def test_delta_indices():
    c = PDPConfig(n_obs_steps=2, horizon=16)
    assert c.observation_delta_indices == [-1, 0]
    assert c.action_delta_indices == list(range(-1, 15))
    assert c.reward_delta_indices is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"latent_dim": 0}, "latent_dim must be >= 1"),
        ({"drop_n_last_frames": -1}, "drop_n_last_frames must be >= 0, got -1"),
        ({"sdtw_gamma": 0.0}, "sdtw_gamma must be > 0"),
        ({"sdtw_gamma": -1.0}, "sdtw_gamma must be > 0"),
        ({"latent_conditioning": "add"}, "latent_conditioning must be one of"),
        ({"latent_type": "vq"}, "latent_type must be one of"),
        ({"horizon": 10}, "horizon (10) must be a multiple"),
        ({"num_inference_steps": 50}, "num_inference_steps (50) must be <="),
        ({"n_action_steps": 16}, "n_action_steps (16) must be <="),
        ({"beta_kl": -1.0}, "beta_kl must be >= 0"),
        ({"steer_latent": [1.0, 2.0, 3.0]}, "steer_latent has 3 values"),
        ({"steer_episode_index": 2}, "steer_episode_index=2 names an episode of no dataset: give steer_dataset_root"),
        ({"steer_dataset_root": "/x", "steer_episode_index": -1}, "steer_episode_index must be an episode index >= 0"),
        ({"trace_normalize": "minmax"}, "trace_normalize must be one of"),
        ({"film_hidden_dims": (16, 0)}, "every entry of film_hidden_dims must be >= 1, got (16, 0)"),
        ({"vae_hidden_dims": (-4,)}, "every entry of vae_hidden_dims must be >= 1"),
        ({"down_dims": ()}, "down_dims must list at least one U-Net level"),
        ({"embed_rec_reduction": "max"}, "embed_rec_reduction must be 'mean' or 'sum', got 'max'"),
        ({"fit_optimizer": "sgd"}, "fit_optimizer must be 'adam' or 'gradient', got 'sgd'"),
        ({"taught_rehearsal_share": 1.0}, "taught_rehearsal_share must be in [0, 1), got 1.0"),
        ({"taught_rehearsal_share": -0.1}, "taught_rehearsal_share must be in [0, 1), got -0.1"),
    ],
)
def test_invalid_values_are_named(kwargs, message):
    with pytest.raises(ValueError, match=None) as e:
        PDPConfig(**kwargs)
    assert message in str(e.value)


def test_presets():
    c = PDPConfig()
    assert c.get_optimizer_preset().lr == c.optimizer_lr
    assert c.get_scheduler_preset().num_warmup_steps == c.scheduler_warmup_steps


def test_affine_film_is_a_valid_choice():
    # () = no hidden layer: z -> (gamma, beta) is one linear map (pick-place's benchmark setting)
    assert tuple(PDPConfig(film_hidden_dims=()).film_hidden_dims) == ()


def test_a_robot_state_under_another_key_is_said_to_condition_nothing(caplog):
    """LeRobot's policies condition on ``observation.state``; a dataset whose robot state sits under another key
    (read as the behavior trace) trains, but the denoiser would not see the state: said in a warning, naming it."""
    import logging

    from lerobot.configs import FeatureType, PolicyFeature

    def features(state_key):
        return {state_key: PolicyFeature(FeatureType.STATE, (3,)),
                "observation.environment_state": PolicyFeature(FeatureType.ENV, (2,))}

    cfg = PDPConfig(trace_key="observation.joint_pos")
    cfg.input_features = features("observation.joint_pos")
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (3,))}
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp"):
        cfg.validate_features()
    assert "['observation.joint_pos'] condition nothing" in caplog.text
    assert "it reads only its behavior trace from trace_key 'observation.joint_pos'" in caplog.text
    assert list(cfg.condition_features) == ["observation.environment_state"]
    caplog.clear()
    cfg.trace_key, cfg.input_features = "observation.state", features("observation.state")
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp"):
        cfg.validate_features()
    assert caplog.text == "" and list(cfg.condition_features) == ["observation.state", "observation.environment_state"]


@pytest.mark.parametrize("config", ["PDPConfig", "PDPReachAroundEnvConfig", "PDPSimConfig", "PDPWaypointsConfig"])
def test_help_of_every_config_pdp_registers_prints(config, capsys):
    """``lerobot-train --policy.type=pdp --help`` (and the env's, robot's, teleoperator's) is built by draccus from the
    fields' comments, which argparse formats with %: a bare % in a comment made --help a TypeError. Every PDP field
    has its help."""
    import dataclasses

    import draccus
    from draccus.wrappers import docstring

    from lerobot_pdp.envs.configs import PDPReachAroundEnvConfig
    from lerobot_pdp.robots.config_pdp_sim import PDPSimConfig
    from lerobot_pdp.teleoperators import PDPWaypointsConfig

    cls = {"PDPConfig": PDPConfig, "PDPReachAroundEnvConfig": PDPReachAroundEnvConfig, "PDPSimConfig": PDPSimConfig,
           "PDPWaypointsConfig": PDPWaypointsConfig}[config]
    with pytest.raises(SystemExit) as done:
        draccus.parse(cls, args=["--help"])
    assert done.value.code == 0 and "usage:" in capsys.readouterr().out
    if cls is PDPConfig:  # LeRobot's own fields (device, push_to_hub, ...) are LeRobot's to document
        own = [f.name for f in dataclasses.fields(cls) if f.init and f.name in vars(cls)["__annotations__"]]
        silent = [n for n in own if not docstring.get_preferred_help_text(docstring.get_attribute_docstring(cls, n))]
        assert not silent, f"PDP fields without help: {silent}"
