"""PDP on camera datasets: image observations condition the denoiser (LeRobot's diffusion image encoder),
demonstrations with cameras are fitted, and bad camera input is refused clearly.

The datasets are the synthetic 4-mode paths with a rendered top-down camera, written as real LeRobotDatasets
(video, as LeRobot stores cameras, or PNG images).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import lerobot_cli, run_cli
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_pdp import PDPConfig, PDPPolicy

from synthetic import camera_image, demo_path, write_dataset

TOP, SIDE = "observation.images.top", "observation.images.side"
SMALL = {"push_to_hub": False, "down_dims": (16, 32), "spatial_softmax_num_keypoints": 8}


@pytest.fixture(scope="module")
def video_dataset(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("cam") / "video", episodes_per_mode=2, cameras=("top",))


@pytest.fixture(scope="module")
def image_dataset(tmp_path_factory):
    """Two cameras stored as PNG images (lossless, so a frame read back equals the rendered one)."""
    return write_dataset(tmp_path_factory.mktemp("cam") / "images", episodes_per_mode=2, cameras=("top", "side"),
                         video=False)


def _meta(root):
    return LeRobotDatasetMetadata("local/synthetic", root=root)


def _batch(root, policy, n=6):
    cfg = policy.config
    meta = _meta(root)
    dt = {k: [i / meta.fps for i in cfg.observation_delta_indices] for k in cfg.input_features}
    dt[ACTION] = [i / meta.fps for i in cfg.action_delta_indices]
    ds = LeRobotDataset("local/synthetic", root=root, delta_timestamps=dt, video_backend="pyav")
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    return pre(torch.utils.data.default_collate([ds[i] for i in range(0, 10 * n, 10)]))


def test_camera_features_condition_the_denoiser_and_train_the_encoder(video_dataset):
    policy = make_policy(PDPConfig(crop_shape=(40, 40), **SMALL), ds_meta=_meta(video_dataset))
    enc = policy.model.obs_encoder
    assert enc.image_keys == [TOP] and enc.vector_keys == [OBS_STATE, OBS_ENV_STATE]
    assert enc.frame_dim == 2 + 2 + 2 * 8
    batch = _batch(video_dataset, policy)
    assert batch[TOP].shape[1:] == (2, 3, 48, 48)
    loss, info = policy.forward(batch)
    loss.backward()
    grads = [p.grad for p in enc.rgb_encoder.parameters() if p.grad is not None]
    assert grads and sum(float(g.abs().sum()) for g in grads) > 0  # L_DP trains the camera encoder
    theta = {id(p) for p in policy.get_optim_params()[1]["params"]}
    assert all(id(p) in theta for p in enc.parameters())
    # the camera changes the action chunk: a different image, same state, other actions
    policy.eval()
    noise = torch.randn(1, policy.config.horizon, 2)
    one = {k: v[:1] for k, v in batch.items() if k in policy.config.condition_features}
    blank = {**one, TOP: torch.zeros_like(one[TOP])}
    policy.set_latent(torch.zeros(2))
    a = policy.model.generate(policy.model.obs_cond(one), torch.zeros(1, 2), noise=noise)
    b = policy.model.generate(policy.model.obs_cond(blank), torch.zeros(1, 2), noise=noise)
    assert not torch.allclose(a, b)


def test_camera_policy_acts_from_a_rollout_observation_stream(video_dataset):
    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    policy.eval()
    batch = _batch(video_dataset, policy, n=3)
    for _ in range(policy.config.n_action_steps + 2):  # a new chunk after the first n_action_steps
        obs = {k: batch[k][:, -1] for k in policy.config.input_features}  # [B, ...] as lerobot-eval sends
        action = policy.select_action(obs)
        assert action.shape == (3, 2) and torch.isfinite(action).all()
    assert len(policy._queues[TOP]) == policy.config.n_obs_steps


def test_fit_latent_on_a_camera_demonstration_reads_its_frames(image_dataset):
    """The fit reads the episode's camera frames from the dataset (PNG images here), and a demonstration
    handed over as arrays (uint8 frames, channel last, as a camera gives them) fits to the same z."""
    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(image_dataset))
    from_disk = policy.fit_latent((image_dataset, 5), steps=4)
    assert from_disk.z.shape == (2,) and torch.isfinite(from_disk.z).all() and len(from_disk.losses) == 4

    ds = LeRobotDataset("local/synthetic", root=image_dataset, episodes=[5])
    states = np.stack([ds[i][OBS_STATE].numpy() for i in range(len(ds))])
    # the same episode as a user holds it: uint8 camera frames, channel last
    episode = {OBS_STATE: states, OBS_ENV_STATE: np.tile([0.0, 1.0], (len(states), 1)),
               ACTION: np.stack([ds[i][ACTION].numpy() for i in range(len(ds))]),
               TOP: np.stack([camera_image(p, 48) for p in states]),
               SIDE: np.stack([camera_image(p, 48) for p in states])}
    from_arrays = policy.fit_latent(episode, steps=4)
    assert torch.allclose(from_arrays.z, from_disk.z, atol=1e-5)
    assert torch.allclose(policy.encode(episode), policy.encode((image_dataset, 5)), atol=1e-6)


def test_a_camera_policy_is_taught_and_taught_again_with_its_frames_kept(image_dataset, tmp_path):
    """Teaching a camera policy keeps the demonstration's frames with the checkpoint (uint8, one 1/255 step), and
    teaching the taught checkpoint again rehearses them; the taught mode acts from camera observations."""
    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(image_dataset))
    first = policy.teach((image_dataset, 5), image_dataset, steps=2, name="episode 5 again")
    policy.save_pretrained(tmp_path / "taught")
    taught = PDPPolicy.from_pretrained(tmp_path / "taught")
    kept = taught.model.bank.taught_demos[first.mode].arrays
    ds = LeRobotDataset("local/synthetic", root=image_dataset, episodes=[5])
    frames = torch.stack([ds[i][TOP] for i in range(len(ds))]).numpy()
    assert kept[TOP].shape == frames.shape and np.abs(kept[TOP] - frames).max() <= 0.5 / 255 + 1e-6
    second = taught.teach((image_dataset, 6), image_dataset, steps=1, name="episode 6 again")
    assert second.rehearsal_windows == first.rehearsal_windows + first.demo_windows  # the first one rehearsed
    taught.set_latent(taught.mode_latents()[first.mode])
    taught.reset()
    obs = {k: ds[0][k][None] for k in taught.config.input_features}
    assert torch.isfinite(taught.select_action(obs)).all()

    # trained further (lerobot-train --policy.path): the kept frames join each batch as the loader's windows would
    cfg = PDPConfig.from_pretrained(tmp_path / "taught")
    cfg.pretrained_path = tmp_path / "taught"
    trained = make_policy(cfg, ds_meta=_meta(image_dataset))
    rehearsal = trained.model.rehearsal
    assert len(rehearsal) == len(ds) and bool((trained.model.bank.mode[rehearsal.rows] == first.mode).all())
    batch = _batch(image_dataset, trained)
    meta = _meta(image_dataset)
    dt = {k: [i / meta.fps for i in cfg.observation_delta_indices] for k in cfg.input_features}
    loader = LeRobotDataset("local/synthetic", root=image_dataset, episodes=[5], video_backend="pyav",
                            delta_timestamps={**dt, ACTION: [i / meta.fps for i in cfg.action_delta_indices]})
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    for t in (0, len(ds) // 2, len(ds) - 1):
        item = pre(torch.utils.data.default_collate([loader[t]]))
        for key, f in rehearsal.frames.items():  # camera frames within the uint8 step the checkpoint keeps them at
            torch.testing.assert_close(f[rehearsal.obs_idx[t]], item[key][0], atol=0.02, rtol=0)
        torch.testing.assert_close(rehearsal.actions[rehearsal.act_idx[t]], item[ACTION][0], atol=1e-5, rtol=1e-5)
        assert torch.equal(rehearsal.is_pad[t], item["action_is_pad"][0])
    trained.train()
    loss, out = trained.forward(batch)
    loss.backward()
    assert np.isfinite(out["loss_dp_taught"])
    assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in trained.model.obs_encoder.parameters())


def test_separate_encoder_per_camera(image_dataset):
    policy = make_policy(PDPConfig(use_separate_rgb_encoder_per_camera=True, **SMALL), ds_meta=_meta(image_dataset))
    assert len(policy.model.obs_encoder.rgb_encoder) == 2
    loss, _ = policy.forward(_batch(image_dataset, policy, n=2))
    assert torch.isfinite(loss)


def test_image_only_and_environment_state_only_conditioning(video_dataset, synthetic_meta):
    """State stays the trace (trace_key) but need not condition the denoiser."""
    meta = _meta(video_dataset)
    feats = {OBS_STATE: PolicyFeature(FeatureType.STATE, (2,)), TOP: PolicyFeature(FeatureType.VISUAL, (3, 48, 48))}
    image_only = make_policy(PDPConfig(condition_on_state=False, input_features=feats, **SMALL), ds_meta=meta)
    assert list(image_only.config.condition_features) == [TOP]
    assert image_only.model.obs_encoder.frame_dim == 16
    batch = _batch(video_dataset, image_only, n=2)
    assert torch.isfinite(image_only.forward(batch)[0])
    image_only.eval()
    assert image_only.select_action({TOP: batch[TOP][:, -1]}).shape == (2, 2)  # no state needed to act
    assert image_only.fit_latent((video_dataset, 2), steps=2).z.shape == (2,)

    env_only = make_policy(PDPConfig(condition_on_state=False, **SMALL), ds_meta=synthetic_meta)
    assert list(env_only.config.condition_features) == [OBS_ENV_STATE]
    assert env_only.model.obs_encoder.frame_dim == 2
    assert env_only.fit_latent((synthetic_meta.root, 0), steps=2).z.shape == (2,)


def test_camera_checkpoint_round_trip(video_dataset, tmp_path):
    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    policy.eval()
    policy.save_pretrained(tmp_path / "ckpt")
    loaded = PDPPolicy.from_pretrained(tmp_path / "ckpt")
    loaded.eval()
    batch = _batch(video_dataset, policy, n=2)
    cond = {k: batch[k] for k in policy.config.condition_features}
    assert torch.allclose(loaded.model.obs_cond(cond), policy.model.obs_cond(cond), atol=1e-6)
    assert torch.allclose(loaded.stats.as_dict()[TOP]["mean"], policy.stats.as_dict()[TOP]["mean"])
    assert loaded.stats.as_dict()[TOP]["mean"].shape == (3, 1, 1)


# ---------------------------------------------------------------------------------------------- bad input


def test_no_trace_key_is_refused_naming_the_keys():
    cfg = PDPConfig(input_features={TOP: PolicyFeature(FeatureType.VISUAL, (3, 48, 48))},
                    output_features={ACTION: PolicyFeature(FeatureType.ACTION, (2,))})
    with pytest.raises(ValueError, match=r"trace_key 'observation.state'.*\['observation.images.top'\]"):
        cfg.validate_features()


def test_cameras_of_different_shapes_are_refused():
    cfg = PDPConfig(input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (2,)),
                                    TOP: PolicyFeature(FeatureType.VISUAL, (3, 48, 48)),
                                    SIDE: PolicyFeature(FeatureType.VISUAL, (3, 64, 64))},
                    output_features={ACTION: PolicyFeature(FeatureType.ACTION, (2,))})
    with pytest.raises(ValueError, match="same shape.*observation.images.side.*64, 64"):
        cfg.validate_features()
    cfg.input_features[SIDE] = PolicyFeature(FeatureType.VISUAL, (3, 48, 48))
    cfg.crop_shape = (56, 56)
    with pytest.raises(ValueError, match=r"crop_shape \(56, 56\) does not fit in the images of "
                                         r"'observation.images.top', 'observation.images.side' \(\(48, 48\)\)"):
        cfg.validate_features()


@pytest.mark.parametrize("separate", [False, True])
def test_cameras_of_different_shapes_are_encoded_with_resize_shape(separate):
    """--policy.resize_shape (what the refusal above advises) brings every camera to one size before the shared
    encoder stacks them (a separate encoder per camera resizes its own)."""
    from lerobot_pdp.observation_encoder import ObservationEncoder

    cfg = PDPConfig(input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (2,)),
                                    TOP: PolicyFeature(FeatureType.VISUAL, (3, 48, 48)),
                                    SIDE: PolicyFeature(FeatureType.VISUAL, (3, 32, 40))},
                    output_features={ACTION: PolicyFeature(FeatureType.ACTION, (2,))}, resize_shape=(40, 40),
                    use_separate_rgb_encoder_per_camera=separate, spatial_softmax_num_keypoints=8)
    cfg.validate_features()
    enc = ObservationEncoder(cfg).eval()
    g = torch.Generator().manual_seed(0)
    batch = {OBS_STATE: torch.zeros(2, 2, 2), TOP: torch.rand(2, 2, 3, 48, 48, generator=g),
             SIDE: torch.rand(2, 2, 3, 32, 40, generator=g)}
    with torch.no_grad():
        out = enc(batch)
    assert out.shape == (2, 2, 2 + 2 * 2 * 8) and torch.isfinite(out).all()


@pytest.mark.parametrize("shape", [{"resize_shape": (32, 32)}, {"crop_shape": (24, 32)}])
def test_frames_the_backbone_maps_to_one_cell_are_refused_for_training(video_dataset, caplog, shape):
    """A 1x1 feature map gives every image the same keypoints: training such a policy is refused, naming the size
    and the fix; a checkpoint already trained so loads with a warning (its cameras never conditioned it)."""
    with pytest.raises(ValueError, match=r"camera frames of \d+x\d+ \((resize|crop)_shape\) leave resnet18 a 1x1 "
                                         r"feature map: .* the cameras condition nothing.*resize_shape='\[64,64\]'"):
        make_policy(PDPConfig(**shape, **SMALL), ds_meta=_meta(video_dataset))
    cfg = make_policy(PDPConfig(crop_shape=(24, 40), **SMALL), ds_meta=_meta(video_dataset)).config  # 1x2: trains
    cfg.crop_shape = None
    for k, v in shape.items():
        setattr(cfg, k, v)
    with caplog.at_level("WARNING", logger="lerobot_pdp.observation_encoder"):
        PDPPolicy(cfg)
    assert any("this checkpoint was trained so" in r.getMessage() for r in caplog.records)


def test_camera_frames_of_the_wrong_shape_or_range_are_refused(video_dataset):
    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    pos, act = demo_path(0, np.random.default_rng(0))
    ep = {OBS_STATE: pos, OBS_ENV_STATE: np.tile([0.0, 1.0], (len(pos), 1)), ACTION: act,
          TOP: np.stack([camera_image(p, 32) for p in pos])}
    with pytest.raises(ValueError, match=r"camera 'observation.images.top' has frames of shape \(\d+, 32, 32, 3\)"):
        policy.fit_latent(ep, steps=1)
    ep[TOP] = np.stack([camera_image(p, 48) for p in pos]).transpose(0, 3, 1, 2).astype(np.float32)  # 0..255
    with pytest.raises(ValueError, match=r"float values in \[.*\]; expected \[0, 1\]"):
        policy.fit_latent(ep, steps=1)
    ep[TOP] = ep[TOP].astype(np.int64)  # integers, not uint8: neither a camera's bytes nor [0, 1]
    with pytest.raises(ValueError, match=r"camera 'observation.images.top' has int64 frames; expected uint8"):
        policy.fit_latent(ep, steps=1)
    del ep[TOP]
    with pytest.raises(KeyError, match="missing 'observation.images.top'"):
        policy.fit_latent(ep, steps=1)
    # an env without the camera (lerobot-eval of a camera checkpoint without --env.camera): the flags are named
    obs = {OBS_STATE: torch.zeros(1, 2), OBS_ENV_STATE: torch.zeros(1, 2)}
    with pytest.raises(KeyError, match=r"which the observation lacks; .*: the env must give this camera \(lerobot_pdp's "
                                       r"envs: --env.camera=top --env.image_size=48, every camera the policy was "
                                       r"trained on\)"):
        policy.select_action(obs)


def test_camera_frames_in_another_layout_are_refused_by_the_preprocessor(video_dataset, tmp_path):
    """What a camera driver gives (uint8, channels last, 0-255, one channel) is named before LeRobot's normaliser,
    which failed on it with a bare torch error or broadcast a one-channel frame to three; the step travels with the
    checkpoint's processors and lets LeRobot's own frames through unchanged."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor import make_default_pre_post_processors

    from lerobot_pdp.processor_pdp import CameraFrameCheck

    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    policy.eval()
    pre, post = make_pre_post_processors(policy.config, dataset_stats=policy.stats.as_dict())
    pre.save_pretrained(tmp_path)
    post.save_pretrained(tmp_path)
    loaded, _ = make_pre_post_processors(policy.config, pretrained_path=str(tmp_path))
    assert [type(s) for s in loaded.steps] == [type(s) for s in pre.steps]
    assert loaded.steps[1] == CameraFrameCheck({TOP: [3, 48, 48]})
    state = {OBS_STATE: torch.zeros(2), OBS_ENV_STATE: torch.zeros(2)}
    frame = torch.rand(3, 48, 48, generator=torch.Generator().manual_seed(0))
    hwc = (frame.permute(1, 2, 0) * 255).to(torch.uint8)
    for image, message in [(hwc, r"is torch.uint8 \[48, 48, 3\]: PDP, as LeRobot's policies, takes float frames in "
                                 r"\[0, 1\], channels first \[..., 3, 48, 48\]"),
                           (hwc.numpy(), r"is uint8 \[48, 48, 3\]"),
                           (hwc.float() / 255, r"has shape \[48, 48, 3\] \(channels last\); this policy expects "
                                               r"\[..., 3, 48, 48\]"),
                           (frame[:1], r"has shape \[1, 48, 48\] \(another size or channel count\); this policy "
                                       r"expects \[..., 3, 48, 48\], its training dataset's frames \(lerobot_pdp's "
                                       r"envs: --env.image_size=48;"),
                           (frame * 255, r"holds values in \[.*\]; camera frames are float in \[0, 1\] \(0-255 values: "
                                         r"divide by 255")]:
        with pytest.raises(ValueError, match=rf"camera '{TOP}' " + message):
            loaded({**state, TOP: image})
    batch = loaded({**state, TOP: frame})  # LeRobot's own frames: through, normalised as before
    lerobots, _ = make_default_pre_post_processors(policy.config, policy.stats.as_dict())
    torch.testing.assert_close(batch[TOP], lerobots({**state, TOP: frame})[TOP], rtol=0, atol=0)
    assert policy.select_action(batch).shape == (1, 2)




def test_fine_tuning_on_frames_of_another_size_is_refused_before_the_behaviours_are_read(video_dataset):
    """lerobot-train --policy.path=<camera checkpoint> on a dataset of another image size: named when the policy is
    built (it failed at the first training step, after the soft-DTW of every behaviour)."""
    import copy
    from types import SimpleNamespace

    policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    features = copy.deepcopy(_meta(video_dataset).features)
    features[TOP]["shape"] = [64, 64, 3]  # stored (H, W, C)
    with pytest.raises(ValueError, match=rf"dataset {video_dataset}: its frames are not the size this policy was "
                                         rf"trained on \('{TOP}' has shape \(3, 64, 64\), the policy was trained on \(3, 48, 48\)\)"):
        PDPPolicy(policy.config, dataset_meta=SimpleNamespace(root=video_dataset, features=features))

def test_the_steering_example_gives_the_env_a_camera_checkpoints_cameras(video_dataset, synthetic_meta):
    """examples/steer_reach_around.py builds its env with every camera the checkpoint was trained on, at its size
    (it built a state-only env, which a camera checkpoint cannot act in)."""
    import importlib.util

    from lerobot.envs.factory import make_env_config

    spec = importlib.util.spec_from_file_location("steer_example", Path(__file__).parents[1] / "examples" /
                                                  "steer_reach_around.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    camera_policy = make_policy(PDPConfig(**SMALL), ds_meta=_meta(video_dataset))
    flags = example.camera_flags(camera_policy)
    assert flags == {"camera": "top", "image_size": "48x48"}
    assert make_env_config("pdp_reach_around", scene="0", **flags).camera == "top"
    assert example.camera_flags(make_policy(PDPConfig(**SMALL), ds_meta=synthetic_meta)) == {}

# ---------------------------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_lerobot_train_on_a_camera_dataset_then_load_fit_and_act(video_dataset, tmp_path):
    """A real lerobot-train process trains PDP on a video camera dataset; the checkpoint loads, fits z to a
    camera episode and acts from camera observations."""
    out = tmp_path / "train"
    run_cli([lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false",
             "--policy.down_dims=[16,32]", "--policy.spatial_softmax_num_keypoints=8", "--policy.crop_shape=[40,40]",
             "--dataset.repo_id=local/synthetic", f"--dataset.root={video_dataset}", "--dataset.video_backend=pyav",
             "--steps=6", "--batch_size=4", "--save_freq=6", "--log_freq=2", "--num_workers=0",
             "--wandb.enable=false", f"--output_dir={out}"], timeout=600)
    ckpt = out / "checkpoints" / "last" / "pretrained_model"
    cfg = json.loads((ckpt / "config.json").read_text())
    assert TOP in cfg["input_features"] and cfg["crop_shape"] == [40, 40]
    policy = PDPPolicy.from_pretrained(ckpt)
    policy.eval()
    res = policy.fit_latent((video_dataset, 3), steps=3)
    assert torch.isfinite(res.z).all() and torch.equal(policy.current_latent()[0], res.z)
    batch = _batch(video_dataset, policy, n=2)
    obs = {k: batch[k][:, -1] for k in policy.config.input_features}
    assert torch.isfinite(policy.select_action(obs)).all()
