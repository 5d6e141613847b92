"""PDP on a CUDA device: training without host syncs, the CUDA-graph sampler, per-phase latents, fitting, and
real ``lerobot-train`` / ``lerobot-eval`` processes with ``--policy.device=cuda``. Skipped without a GPU."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import lerobot_cli, run_cli
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from policies import small_policy, training_batch

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def test_training_step_runs_on_the_gpu_without_host_syncs(synthetic_meta):
    p = small_policy(synthetic_meta, "cuda")
    p.train()
    batch = training_batch(synthetic_meta, p)
    assert batch[ACTION].is_cuda and p.model.bank.traces.is_cuda and p.model.bank.distances.is_cuda
    p.model.loss_terms(batch)  # first call: lazy CUDA initialisation may synchronise
    torch.cuda.set_sync_debug_mode("error")
    try:
        loss, metrics = p.model.loss_terms(batch)
        loss.backward()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert {"loss_dp", "embed_rec", "embed_kl", "embed_geo", "loss_embed"} <= set(metrics)
    loss2, info = p.forward(batch)  # LeRobot's face: plain floats, read back in one transfer
    assert all(isinstance(v, float) for v in info.values()) and torch.isfinite(loss2)


def test_graphed_training_step_matches_eager_and_replays_without_host_syncs(synthetic_meta):
    """train_cuda_graphs (the default on CUDA): forward and backward replayed from captured graphs give the
    eager loss, logged terms and gradients from the same generator state, step after step with the weights
    updated in between; a replay never waits for the GPU; another batch size gets its own graphs."""
    graphed = small_policy(synthetic_meta, "cuda")
    eager = small_policy(synthetic_meta, "cuda", train_cuda_graphs=False)
    eager.load_state_dict(graphed.state_dict())
    batch = training_batch(synthetic_meta, graphed, n=8)
    small = training_batch(synthetic_meta, graphed, n=5, seed=1)  # an epoch's last, smaller batch
    opts = {}
    for q in (graphed, eager):
        q.train()
        opts[q] = torch.optim.AdamW(q.get_optim_params(), lr=1e-3)
    for step, b in enumerate((batch, batch, small, batch)):
        out = []
        for q in (graphed, eager):
            torch.manual_seed(step)
            loss, info = q.forward(b)
            loss.backward()
            out.append((loss.detach().clone(), info, [x.grad.clone() for x in q.parameters() if x.grad is not None]))
            opts[q].step()
            opts[q].zero_grad(set_to_none=True)
        (lg, ig, gg), (le, ie, ge) = out
        # same kernels on the same inputs and generator state: equal up to reduction order (1e-5)
        torch.testing.assert_close(lg, le, atol=1e-5, rtol=1e-5)
        assert ig.keys() == ie.keys() and all(abs(ig[k] - ie[k]) <= 1e-5 * (1 + abs(ie[k])) for k in ie)
        assert len(gg) == len(ge) > 0
        for a, e in zip(gg, ge, strict=True):
            torch.testing.assert_close(a, e, atol=1e-5, rtol=1e-4)
    assert len(graphed.model._train_graphs._steps) == 2  # batch sizes 8 and 5
    assert torch.isfinite(graphed.model.train_loss_dp)
    torch.testing.assert_close(graphed.model.train_loss_dp, eager.model.train_loss_dp, atol=1e-5, rtol=1e-5)
    torch.cuda.set_sync_debug_mode("error")
    try:
        loss, _ = graphed.model.loss_terms(batch)
        loss.backward()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    graphed.eval()  # evaluation: eager, not a training graph
    with torch.no_grad():
        graphed.model.loss_terms(batch)
    assert len(graphed.model._train_graphs._steps) == 2


def _sampler_inputs(p, batch: int, seed: int):
    """Random (obs condition, z, initial noise) for ``p``'s sampler on the GPU."""
    g = torch.Generator(device="cuda").manual_seed(seed)
    return (torch.randn(batch, p.model.denoiser.obs_cond_dim, device="cuda", generator=g),
            torch.randn(batch, p.config.latent_dim, device="cuda", generator=g),
            torch.randn(batch, p.config.horizon, p.action_dim, device="cuda", generator=g))


def test_graphed_sampler_matches_eager_and_follows_weight_updates(synthetic_meta):
    p = small_policy(synthetic_meta, "cuda")
    p.eval()
    obs, z, noise = _sampler_inputs(p, 3, seed=0)
    n = p.config.num_inference_steps
    for _ in range(2):  # capture, then replay
        torch.testing.assert_close(p.generate(obs, z, noise=noise), p.model._sample(obs, z, noise, n), atol=1e-5, rtol=1e-5)
    assert len(p.model._graphs._calls) == 1
    torch.cuda.set_sync_debug_mode("error")  # a replayed chunk never waits for the GPU
    try:
        p.generate(obs, z, noise=noise)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    with torch.no_grad():  # an optimizer step changes the weights in place: the graph is captured anew
        for q in p.model.denoiser.parameters():
            q.add_(0.01 * torch.randn_like(q))
    torch.testing.assert_close(p.generate(obs, z, noise=noise), p.model._sample(obs, z, noise, n), atol=1e-5, rtol=1e-5)
    out = p.generate(obs, z + 1.0, noise=noise)  # a new z through the same graph
    torch.testing.assert_close(out, p.model._sample(obs, z + 1.0, noise, n), atol=1e-5, rtol=1e-5)


def test_a_real_time_chunking_prefix_replays_from_the_sampler_graph(synthetic_meta):
    """A chunk guided towards the previous chunk's actions (real-time chunking, the policy server's carried
    actions) is replayed from a captured graph whose inputs are the prefix's target and weights: the eager
    guided chunk, without a host sync, and another prefix through the same graph."""
    from lerobot_pdp.diffusion import PrefixGuide

    p = small_policy(synthetic_meta, "cuda")
    p.eval()
    obs, z, noise = _sampler_inputs(p, 2, seed=3)
    n = p.config.num_inference_steps
    weight = torch.linspace(1, 0, p.config.horizon, device="cuda")[None, :, None]
    prefix = PrefixGuide(torch.randn_like(noise), weight)
    for _ in range(2):  # capture, then replay
        torch.testing.assert_close(p.generate(obs, z, noise=noise, guide=prefix),
                                   p.model._sample(obs, z, noise, n, prefix), atol=1e-5, rtol=1e-5)
    assert len(p.model._graphs._calls) == 1
    other = PrefixGuide(torch.randn_like(noise), weight.flip(1))
    torch.cuda.set_sync_debug_mode("error")
    try:
        got = p.generate(obs, z, noise=noise, guide=other)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.testing.assert_close(got, p.model._sample(obs, z, noise, n, other), atol=1e-5, rtol=1e-5)
    assert len(p.model._graphs._calls) == 1


def test_a_background_fit_beside_sampler_captures(synthetic_meta):
    """Live steering fits a latent in a background thread while the control loop acts: graph captures of new
    sampler shapes during the fit neither fail (the sampler would act eagerly from then on) nor fail the fit
    (its memory allocations are another thread's work during a capture)."""
    from lerobot_pdp.steering import BackgroundFit

    p = small_policy(synthetic_meta, "cuda")
    p.eval()
    n = p.config.num_inference_steps
    fit = BackgroundFit(p, synthetic_meta.root, 3, steps=300)
    captures = 0
    while not fit.done() or captures < 4:
        obs, z, noise = _sampler_inputs(p, 1 + captures % 6, seed=captures)  # a new shape: captured anew
        torch.testing.assert_close(p.generate(obs, z, noise=noise), p.model._sample(obs, z, noise, n),
                                   atol=1e-5, rtol=1e-5)
        captures += 1
    assert fit.wait(60) and fit.error is None, fit.error
    assert torch.isfinite(fit.result.z).all() and len(fit.result.losses) == 300
    assert p.model._cuda_graphs, "a capture failed during the fit: the sampler fell back to eager kernels"


def test_gpu_sampler_matches_a_float64_reference(synthetic_meta):
    """The GPU sampler (precomputed modulation, PyTorch's cuDNN convolutions) against the same sampler run in
    float64. cuDNN's float32 algorithms differ by GPU and version (on an H200: 3.3e-5 from float64 after 20
    steps); a wrong modulation layout is off by O(0.1)."""
    import copy

    torch.manual_seed(0)  # the CPU test's weights (built on the CPU, then moved)
    p = small_policy(synthetic_meta, "cuda")
    p.eval()
    ref = copy.deepcopy(p.model).double()  # before any sampling: no cached graphs or constants to copy
    obs, z, noise = _sampler_inputs(p, 2, seed=1)
    n = p.config.num_inference_steps
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False  # lerobot-train and lerobot-eval turn it on
    try:
        with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # float32 arithmetic
            want = ref._sample(obs.double(), z.double(), noise.double(), n)
            got = p.model._sample(obs, z, noise, n)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
    assert (got.double() - want).abs().max().item() <= 2e-4


@pytest.mark.parametrize("mode", ["default", "reduce-overhead"])
def test_compiled_policy_on_the_gpu(synthetic_meta, mode):
    """compile_model on CUDA: the compiled sampler step inside PDP's captured graph gives the eager chunk and
    replays without a host sync; the compiled training step gives the eager loss and gradients."""
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # exact arithmetic on both paths
        _check_compiled_policy(synthetic_meta, mode)


def _check_compiled_policy(synthetic_meta, mode: str) -> None:
    eager = small_policy(synthetic_meta, "cuda", train_cuda_graphs=False)
    p = small_policy(synthetic_meta, "cuda", compile_model=True, compile_mode=mode)
    p.load_state_dict(eager.state_dict())
    for q in (eager, p):
        q.eval()
    obs, z, noise = _sampler_inputs(p, 1, seed=2)
    want = eager.model._sample(obs, z, noise, p.config.num_inference_steps)
    for _ in range(2):  # capture (compiling in the warm-up), then replay
        torch.testing.assert_close(p.generate(obs, z, noise=noise), want, atol=1e-4, rtol=1e-4)
    torch.cuda.set_sync_debug_mode("error")
    try:
        p.generate(obs, z, noise=noise)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    batch = training_batch(synthetic_meta, p)
    for q in (eager, p):
        q.train()
    for step in range(3):  # compile, then (reduce-overhead) record and replay its CUDA graphs
        losses, grads = [], []
        for q in (eager, p):
            q.zero_grad()
            torch.manual_seed(step)
            loss, _ = q.model.loss_terms(batch)
            loss.backward()
            losses.append(loss.detach().clone())
            grads.append([x.grad.clone() for x in q.model.denoiser.parameters()])
        torch.testing.assert_close(losses[1], losses[0], atol=1e-4, rtol=1e-4)
        for a, b in zip(*grads, strict=True):
            torch.testing.assert_close(b, a, atol=1e-4, rtol=1e-3)
    assert set(p.model._compiled_fns) == {"sample", "train"}


def test_per_phase_latents_advance_on_the_gpu(synthetic_meta):
    """Several select_action calls with one latent per phase (the second call used to mix devices)."""
    p = small_policy(synthetic_meta, "cuda", n_action_steps=2)
    p.eval()
    p.config.segment_gripper_dim = 0  # stand-in gripper: the sign of the raw x action
    p.config.phase_switch_steps = 1
    p.set_latent(torch.tensor([[0.0, 1.0], [1.0, 0.0]]))
    p.reset()
    batch = {OBS_STATE: torch.zeros(2, 2, device="cuda"), OBS_ENV_STATE: torch.zeros(2, 2, device="cuda")}
    for _ in range(6):
        a = p.select_action(batch)
        assert a.is_cuda and a.shape == (2, 2)
    assert p.phases.phase.is_cuda and p.current_latent(2).is_cuda


def test_camera_policy_trains_acts_and_fits_on_the_gpu(tmp_path):
    """Cameras: the image encoder on the GPU, a training step without host syncs, acting, fitting."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from synthetic import write_dataset

    root = write_dataset(tmp_path / "cam", episodes_per_mode=1, cameras=("top",), video=False)
    meta = LeRobotDatasetMetadata("local/synthetic", root=root)
    p = small_policy(meta, "cuda", spatial_softmax_num_keypoints=8, crop_shape=(40, 40))
    assert all(q.is_cuda for q in p.model.obs_encoder.parameters())
    p.train()
    batch = training_batch(meta, p)
    assert batch["observation.images.top"].is_cuda
    p.model.loss_terms(batch)
    torch.cuda.set_sync_debug_mode("error")
    try:
        loss, _ = p.model.loss_terms(batch)
        loss.backward()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    p.eval()
    p.reset()
    for _ in range(p.config.n_action_steps + 1):
        action = p.select_action({k: batch[k][:2, -1] for k in p.config.input_features})
        assert action.is_cuda and action.shape == (2, 2)
    res = p.fit_latent((root, 1), steps=3)
    assert torch.isfinite(res.z).all() and p.current_latent().is_cuda


def test_fit_latent_on_the_gpu(synthetic_meta):
    p = small_policy(synthetic_meta, "cuda")
    res = p.fit_latent((synthetic_meta.root, 3), steps=5)
    assert torch.isfinite(res.z).all() and len(res.losses) == 5
    assert p.active_latent.is_cuda
    p.reset()
    obs = {OBS_STATE: torch.zeros(1, 2, device="cuda"), OBS_ENV_STATE: torch.zeros(1, 2, device="cuda")}
    assert p.select_action(obs).is_cuda


def test_fit_noise_chunks_on_the_gpu(synthetic_meta):
    """fit_latent(noise="chunks") on CUDA: the noises are fitted and kept on the device, and the graphed
    sampler starts the next chunks from them as the eager CPU path does."""
    p = small_policy(synthetic_meta, "cuda")
    p.eval()
    res = p.fit_latent((synthetic_meta.root, 3), steps=2, noise="chunks")
    assert res.noise.is_cuda and p.active_noise.is_cuda and torch.isfinite(res.noise).all()
    obs = {OBS_STATE: torch.zeros(1, p.config.n_obs_steps, 2, device="cuda"),
           OBS_ENV_STATE: torch.zeros(1, p.config.n_obs_steps, 2, device="cuda")}
    p.reset()
    first = p.predict_action_chunk(obs)
    torch.testing.assert_close(first, p.predict_action_chunk(obs, noise=res.noise[:1]), atol=1e-4, rtol=1e-4)


@pytest.mark.slow
def test_lerobot_train_and_eval_on_cuda_with_phase_latents(tmp_path):
    """Pick-place (one latent per reach / carry phase): the benchmark's lerobot-train command on CUDA, then
    lerobot-eval on CUDA steering a mode's per-phase latents."""
    from lerobot_pdp.benchmark.settings import SETTINGS, methods_for
    from lerobot_pdp.benchmark.training import train_method
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.envs.recording import make_dataset

    suite = get_suite_env("pick-place")
    data = make_dataset("pick-place", tmp_path / "data", scene=0, episodes_per_mode=1, seed=0, progress=False)
    settings = SETTINGS["pick-place"][1]
    ckpt = train_method(methods_for(suite)["pdp"], data, tmp_path / "run", 0, settings, 40, device="cuda")
    info = json.loads((tmp_path / "run" / "train_info.json").read_text())
    assert "--policy.device=cuda" in info["args"]
    out = tmp_path / "eval"
    run_cli([lerobot_cli("lerobot-eval"), f"--policy.path={ckpt}", "--policy.device=cuda",
             "--env.type=pdp_pick_place", "--env.scene=0", "--policy.steer_mode=5", "--eval.n_episodes=2",
             "--eval.batch_size=2", f"--output_dir={out}"], timeout=900)
    assert json.loads((out / "eval_info.json").read_text())["overall"]["n_episodes"] == 2
