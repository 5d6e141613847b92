"""Benchmark baselines: the mlp_bc LeRobot plugin, DP's matching config, DP noise-space adaptation
(weights frozen), FixedNoisePolicy and BC fine-tuning (on a copy)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import lerobot_cli, run_cli
from lerobot.configs import PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_policy, make_pre_post_processors

from lerobot_pdp import PDPConfig
from lerobot_pdp.baselines import MLPBCConfig, MLPBCPolicy
from lerobot_pdp.benchmark.baselines import (
    FixedNoisePolicy,
    adapt_dp_noise,
    demo_batch,
    dp_config_kwargs,
    dp_config_matching,
    dp_noise_matching_loss,
    finetune_bc,
)
from lerobot_pdp.envs.recording import make_dataset
from lerobot_pdp.episodes import read_episodes

KEYS = ["observation.state", "observation.environment_state", "action"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def reach_root(tmp_path_factory) -> Path:
    """Reach-around scene 0, one demonstration per mode (8 episodes)."""
    return make_dataset(env="reach-around", out=tmp_path_factory.mktemp("bl") / "reach", scene=0,
                        episodes_per_mode=1, seed=0, progress=False)


@pytest.fixture(scope="module")
def reach_meta(reach_root):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    return LeRobotDatasetMetadata("local/reach", root=reach_root)


@pytest.fixture(scope="module")
def episode(reach_root) -> dict[str, np.ndarray]:
    ep = read_episodes(reach_root, KEYS, [2])[2]
    return {k: ep[k] for k in KEYS}


def _bc(meta, **kw):
    torch.manual_seed(0)
    cfg = MLPBCConfig(device="cpu", push_to_hub=False, **kw)
    policy = make_policy(cfg, ds_meta=meta)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return policy, pre, post


def _dp(meta, **kw):
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    torch.manual_seed(0)
    cfg = DiffusionConfig(device="cpu", push_to_hub=False, **dp_config_kwargs({"down_dims": (16, 32), **kw}))
    policy = make_policy(cfg, ds_meta=meta)
    policy.eval()
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return policy, pre, post


def _obs(episode, frame: int, batch: int = 1) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(episode[k][frame], dtype=torch.float32).expand(batch, -1).clone() for k in KEYS[:2]}


# ----------------------------------------------------------------------------- mlp_bc plugin


def test_mlp_bc_registered_and_resolved_by_lerobot_factory():
    assert "mlp_bc" in PreTrainedConfig.get_known_choices()
    assert PreTrainedConfig.get_choice_class("mlp_bc") is MLPBCConfig
    assert get_policy_class("mlp_bc") is MLPBCPolicy
    cfg = MLPBCConfig()
    assert (cfg.n_obs_steps, cfg.horizon, cfg.n_action_steps, cfg.optimizer_lr) == (2, 16, 8, 1e-4)
    assert {k: v.value for k, v in cfg.normalization_mapping.items()} == {
        "STATE": "MIN_MAX", "ENV": "MIN_MAX", "ACTION": "MIN_MAX"}
    with pytest.raises(ValueError, match="n_action_steps"):
        MLPBCConfig(n_action_steps=16)


def test_mlp_bc_from_dataset_meta_trains_and_acts(reach_meta, episode):
    policy, pre, post = _bc(reach_meta)
    assert isinstance(policy, MLPBCPolicy)
    n_params = sum(p.numel() for p in policy.parameters())
    assert 0.8e6 < n_params < 1.6e6, n_params  # comparable to PDP's default denoiser (~1.2 M)
    assert [type(s).__name__ for s in pre.steps][-1] == "NormalizerProcessorStep"

    batch = demo_batch(policy, pre, episode)
    T = len(episode["action"])
    assert batch["observation.state"].shape == (T, 2, 6)
    assert batch["observation.environment_state"].shape == (T, 2, 6)
    assert batch["action"].shape == (T, 16, 3) and batch["action_is_pad"].shape == (T, 16)
    policy.train()
    loss, info = policy.forward(batch)
    assert torch.isfinite(loss) and info["mse"] == pytest.approx(loss.item())
    loss.backward()
    assert all(p.grad is not None for p in policy.parameters())

    policy.eval()
    policy.reset()
    chunk = policy.predict_action_chunk({k: batch[k][:4] for k in KEYS[:2]})
    assert chunk.shape == (4, 8, 3) and chunk.abs().max() <= 1.0
    policy.reset()
    actions = [policy.select_action(pre(_obs(episode, t, batch=3))) for t in range(9)]
    assert all(a.shape == (3, 3) for a in actions)
    assert len(policy._queues["action"]) == 8 - 1  # 9 calls: a chunk of 8, then a new one
    assert post(actions[0]).shape == (3, 3)


def test_demo_batch_matches_lerobot_dataset_windows(reach_root, reach_meta, episode):
    """The adaptation windows are exactly what the training loader yields (incl. clamping and padding)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    policy, pre, _ = _bc(reach_meta)
    cfg = policy.config
    fps = reach_meta.fps
    ds = LeRobotDataset("local/reach", root=reach_root, delta_timestamps={
        **{k: [i / fps for i in cfg.observation_delta_indices] for k in KEYS[:2]},
        "action": [i / fps for i in cfg.action_delta_indices],
    })
    start = int(ds.meta.episodes["dataset_from_index"][2])
    T = len(episode["action"])
    ours = demo_batch(policy, pre, episode)
    for t in (0, 1, T // 2, T - 3, T - 1):
        item = pre(torch.utils.data.default_collate([ds[start + t]]))
        for k in KEYS:
            torch.testing.assert_close(ours[k][t], item[k][0], atol=1e-5, rtol=1e-5)
        assert torch.equal(ours["action_is_pad"][t], item["action_is_pad"][0])
    assert ours["action_is_pad"][T - 1].sum() == 16 - 2  # only the last frame and the one before it are real


# ----------------------------------------------------------------------------- DP


def test_dp_config_matching_gives_pdp_backbone_and_ddim():
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    args = dp_config_matching({})
    assert "--policy.down_dims=[32,64,128]" in args
    assert "--policy.noise_scheduler_type=DDIM" in args
    assert all(a.startswith("--policy.") and "=" in a for a in args)
    kw = dp_config_kwargs({})
    cfg = DiffusionConfig(**kw)
    expected = dict(down_dims=(32, 64, 128), horizon=16, n_obs_steps=2, n_action_steps=8, noise_scheduler_type="DDIM",
                    num_train_timesteps=20, num_inference_steps=PDPConfig().num_inference_steps, kernel_size=5, n_groups=8,
                    diffusion_step_embed_dim=64)
    assert {k: getattr(cfg, k) for k in expected} == expected
    # a PDP config's own values win (extra PDP-only keys are ignored)
    from dataclasses import asdict

    kw = dp_config_kwargs(asdict(PDPConfig(down_dims=(16, 32), horizon=8, n_action_steps=4, num_inference_steps=5)))
    assert (kw["down_dims"], kw["horizon"], kw["num_inference_steps"]) == ((16, 32), 8, 5)
    assert "--policy.horizon=8" in dp_config_matching(PDPConfig(horizon=8, n_action_steps=4))
    # padding: DP trains (and adapts) on copy-padded steps exactly when PDP does
    assert dp_config_kwargs(PDPConfig())["do_mask_loss_for_padding"] is True
    assert dp_config_kwargs(PDPConfig(do_mask_loss_for_padding=False))["do_mask_loss_for_padding"] is False
    # the forward process too: a "linear" PDP's betas are DP's (a legacy one's scaled end is passed as it is)
    lin = DiffusionConfig(**dp_config_kwargs(PDPConfig(beta_schedule="linear", beta_end=0.03)))
    assert (lin.beta_schedule, lin.beta_start, lin.beta_end) == ("linear", 1e-4, 0.03)
    assert dp_config_kwargs(PDPConfig(beta_schedule="linear", beta_end=None))["beta_end"] == pytest.approx(0.1)
    assert "beta_end" not in kw  # cosine: no betas to match, and DP's recorded command lines keep their flags


def test_adapt_dp_noise_lowers_matching_loss_and_freezes_weights(reach_meta, episode):
    policy, pre, _ = _dp(reach_meta)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    flags = [p.requires_grad for p in policy.parameters()]
    x0 = torch.randn(1, 16, 3, generator=torch.Generator().manual_seed(0))  # adapt_dp_noise's own start
    noise = adapt_dp_noise(policy, pre, episode, steps=8, lr=0.1, batch_size=16, seed=0)
    assert noise.shape == (1, 16, 3) and not noise.requires_grad
    assert not torch.equal(noise, x0)
    assert dp_noise_matching_loss(policy, pre, episode, noise) < dp_noise_matching_loss(policy, pre, episode, x0)
    after = policy.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert all(p.grad is None for p in policy.parameters())
    assert [p.requires_grad for p in policy.parameters()] == flags
    assert not policy.training
    # deterministic given the seed
    again = adapt_dp_noise(policy, pre, episode, steps=8, lr=0.1, batch_size=16, seed=0)
    torch.testing.assert_close(again, noise)


@pytest.mark.numerics
def test_dp_noise_matching_counts_padded_steps_as_dp_was_trained(reach_meta, episode):
    policy, pre, _ = _dp(reach_meta)
    noise = torch.randn(1, 16, 3, generator=torch.Generator().manual_seed(0))
    # Reference: LeRobot's own sampler on every window, errors averaged by hand.
    batch = demo_batch(policy, pre, episode)
    with torch.no_grad():
        cond = policy.diffusion._prepare_global_conditioning(batch)
        pred = policy.diffusion.conditional_sample(len(cond), global_cond=cond, noise=noise.expand(len(cond), -1, -1))
    err = (pred - batch["action"]).pow(2).mean(-1)  # [N, horizon]
    keep = ~batch["action_is_pad"].bool()
    assert not keep.all()  # the episode's last windows run past its end
    expected = {False: float(err.mean()), True: float(err[keep].mean())}
    for masked in (False, True):
        policy.config.do_mask_loss_for_padding = masked
        assert dp_noise_matching_loss(policy, pre, episode, noise) == pytest.approx(expected[masked], rel=1e-5)


def test_adapt_dp_noise_rejects_non_diffusion_policy(reach_meta, episode):
    policy, pre, _ = _bc(reach_meta)
    with pytest.raises(TypeError, match="DiffusionPolicy"):
        adapt_dp_noise(policy, pre, episode, steps=1)


@pytest.mark.numerics
def test_fixed_noise_policy_passes_its_noise(reach_meta, episode):
    policy, pre, _ = _dp(reach_meta)
    noise = torch.randn(1, 16, 3, generator=torch.Generator().manual_seed(1))
    wrapped = FixedNoisePolicy(policy, noise)
    assert isinstance(wrapped, torch.nn.Module) and wrapped.config is policy.config

    seen = []
    original = policy.select_action

    def spy(batch, noise=None):
        seen.append(noise)
        return original(batch, noise=noise)

    policy.select_action = spy
    wrapped.reset()
    obs = pre(_obs(episode, 0, batch=3))
    a = wrapped.select_action(obs)
    assert a.shape == (3, 3)
    assert seen[0].shape == (3, 16, 3) and torch.equal(seen[0][2], noise[0])
    del policy.select_action
    # same as calling the DP with that noise directly; same noise -> same action every reset
    policy.reset()
    direct = policy.select_action(pre(_obs(episode, 0, batch=3)), noise=noise.expand(3, -1, -1))
    torch.testing.assert_close(a, direct)
    wrapped.reset()
    torch.testing.assert_close(wrapped.select_action(pre(_obs(episode, 0, batch=3))), a)
    assert all(torch.equal(seen[0][i], noise[0]) for i in range(3))  # one noise for all envs of the batch
    # and so one action: each row is the same computation at another batch position, which BLAS kernels may
    # round differently (up to 2.7e-6 apart across CPU code paths, after the sampler's steps): 1e-4
    torch.testing.assert_close(a[1:], a[:1].expand(2, -1), atol=1e-4, rtol=0)


def test_per_chunk_noise_is_fitted_per_chunk_and_played_in_order(reach_meta, episode):
    """per_chunk: one noise per executed chunk of the demo (n_action_steps = 8 frames each); the wrapper
    hands noise j to the j-th generated chunk and repeats the last one, from the first again after reset."""
    policy, pre, _ = _dp(reach_meta)
    T = len(episode["action"])
    seq = adapt_dp_noise(policy, pre, episode, steps=4, lr=0.1, batch_size=16, seed=0, per_chunk=True)
    assert seq.shape == (-(-T // 8), 16, 3) and not torch.equal(seq[0], seq[1])
    wrapped = FixedNoisePolicy(policy, seq[:2])
    seen = []
    original = policy.select_action

    def spy(batch, noise=None):
        if len(policy._queues["action"]) == 0:
            seen.append(noise[0].clone())
        return original(batch, noise=noise)

    policy.select_action = spy
    for _ in range(2):
        wrapped.reset()
        seen.clear()
        for t in range(3 * 8):
            wrapped.select_action(pre(_obs(episode, t, batch=2)))
        assert len(seen) == 3
        assert torch.equal(seen[0], seq[0]) and torch.equal(seen[1], seq[1]) and torch.equal(seen[2], seq[1])
    del policy.select_action


# ----------------------------------------------------------------------------- BC


def test_finetune_bc_changes_copy_not_original(reach_meta, episode):
    policy, pre, _ = _bc(reach_meta, hidden_dims=(64, 64))
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    batch = demo_batch(policy, pre, episode)
    loss0 = policy.forward(batch)[0].item()
    tuned = finetune_bc(policy, pre, episode, steps=20, lr=1e-3, batch_size=16, seed=0)
    assert tuned is not policy and isinstance(tuned, MLPBCPolicy) and not tuned.training
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())
    assert all(p.grad is None for p in policy.parameters())
    assert any(not torch.equal(before[k], v) for k, v in tuned.state_dict().items())
    assert tuned.forward(batch)[0].item() < loss0
    # default: small learning rate -> small change
    small = finetune_bc(policy, pre, episode, steps=5, seed=0)
    delta = max((before[k] - v).abs().max().item() for k, v in small.state_dict().items())
    assert 0 < delta < 1e-3


# ----------------------------------------------------------------------------- real lerobot-train


@pytest.mark.slow
def test_lerobot_train_mlp_bc_and_matched_dp(reach_root, episode, tmp_path):
    """`lerobot-train --policy.type=mlp_bc` finds the plugin; DP trains on state + env state with DDIM."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    common = ["--policy.push_to_hub=false", "--policy.device=cpu", "--dataset.repo_id=local/reach",
              f"--dataset.root={reach_root}", "--steps=6", "--batch_size=8", "--log_freq=3", "--save_freq=6",
              "--num_workers=0", "--wandb.enable=false", "--seed=0"]
    runs = {"mlp_bc": ["--policy.type=mlp_bc"], "diffusion": ["--policy.type=diffusion", *dp_config_matching({})]}
    for name, args in runs.items():
        out = tmp_path / name
        run_cli([lerobot_cli("lerobot-train"), *args, *common, f"--output_dir={out}"], timeout=600)
        ckpt = out / "checkpoints" / "last" / "pretrained_model"
        cfg = PreTrainedConfig.from_pretrained(ckpt)
        assert cfg.type == name
        policy = get_policy_class(cfg.type).from_pretrained(ckpt)
        policy.eval()
        pre, post = make_pre_post_processors(cfg, pretrained_path=str(ckpt))
        policy.reset()
        action = post(policy.select_action(pre(_obs(episode, 0))))
        assert action.shape == (1, 3) and torch.isfinite(action).all()
        if name == "diffusion":
            assert isinstance(policy, DiffusionPolicy)
            assert type(policy.diffusion.noise_scheduler).__name__ == "DDIMScheduler"
            assert policy.diffusion.num_inference_steps == PDPConfig().num_inference_steps and cfg.down_dims == (32, 64, 128)


# ----------------------------------------------------------------------------- VQ-BeT (camera variant)


def test_vqbet_demo_windows_and_finetuning_keep_its_codebook(tmp_path):
    """LeRobot's vqbet on a camera demonstration: its action window (3 tokens x 5 actions after 2 observation
    frames) is cut like the loader's, and fine-tuning changes its GPT but not its residual codebook."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.vqbet.configuration_vqbet import VQBeTConfig

    from lerobot_pdp.benchmark.data import demo_episode

    root = make_dataset(env="reach-around", out=tmp_path / "cam", scene=0, episodes_per_mode=1, modes=[0],
                        seed=0, progress=False, camera="oblique", image_size=32)
    meta = LeRobotDatasetMetadata("local/cam", root=root)
    torch.manual_seed(0)
    cfg = VQBeTConfig(device="cpu", push_to_hub=False, n_obs_steps=2, crop_shape=None, pretrained_backbone_weights=None,
                      use_group_norm=True, n_vqvae_training_steps=1, vqvae_embedding_dim=16, vqvae_enc_hidden_dim=16,
                      gpt_input_dim=32, gpt_output_dim=32, gpt_hidden_dim=32, gpt_n_layer=1, gpt_n_head=2)
    policy = make_policy(cfg, ds_meta=meta)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    demo = demo_episode(root)
    T = len(demo["action"])
    batch = demo_batch(policy, pre, demo)
    assert batch["action"].shape == (T, 2 - 1 + 3 + 5 - 1, 3)  # range(1 - n_obs, tokens + chunk - 1)
    assert batch["observation.images.oblique"].shape == (T, 2, 3, 32, 32)
    policy.train()
    policy.forward(batch)  # the one VQ-VAE step: the codebook is frozen from here on
    assert bool(policy.vqbet.action_head.vqvae_model.discretized)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    tuned = finetune_bc(policy, pre, demo, steps=3, lr=1e-3, batch_size=8, seed=0)
    after = tuned.state_dict()
    codebook = [k for k in after if ".vq_layer." in k and after[k].is_floating_point()]
    gpt = [k for k in after if ".policy." in k and k.endswith("weight")]
    assert codebook and gpt
    assert all(torch.equal(before[k], after[k]) for k in codebook)
    assert any(not torch.equal(before[k], after[k]) for k in gpt)
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())  # the original untouched
