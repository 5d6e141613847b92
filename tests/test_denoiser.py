"""FiLM U-Net denoiser and noise schedule."""

import pickle

import pytest
import torch

from lerobot_pdp.denoiser import FiLMUnet1d, LatentFiLM, NoiseSchedule
from lerobot_pdp.diffusion import PrefixGuide
from lerobot_pdp.fast_inference import FastDenoiser, FrozenDenoiser


def _net(mode="film", film_hidden_dims=(16, 32)):
    torch.manual_seed(0)
    return FiLMUnet1d(action_dim=3, obs_cond_dim=10, latent_dim=2, latent_conditioning=mode, down_dims=(16, 32),
                      film_hidden_dims=film_hidden_dims)


@pytest.mark.parametrize("mode", ["film", "concat", "input", "none"])
def test_shapes(mode):
    net = _net(mode)
    x = torch.randn(4, 16, 3)
    out = net(x, torch.randint(0, 20, (4,)), torch.randn(4, 10), torch.randn(4, 2))
    assert out.shape == x.shape


def test_film_is_identity_at_init_and_z_matters_after_training_its_mlp():
    film = LatentFiLM(2, 8, (16, 32))
    gamma, beta = film(torch.randn(5, 2))
    assert torch.equal(gamma, torch.ones(5, 8, 1)) and torch.equal(beta, torch.zeros(5, 8, 1))
    net = _net("film")
    blocks = [m for m in net.modules() if isinstance(m, LatentFiLM)]
    # every residual block has its own z-modulation (paper: "at multiple layers")
    assert len(blocks) == sum(1 for m in net.modules() if m.__class__.__name__ == "ConditionalResidualBlock1d")
    for b in blocks:
        torch.nn.init.normal_(b.mlp[-1].weight, std=0.5)
    x, k, c = torch.randn(2, 16, 3), torch.tensor([5, 5]), torch.randn(1, 10).expand(2, -1)
    out = net(x[:1].expand(2, -1, -1), k, c, torch.tensor([[0.0, 0.0], [2.0, -2.0]]))
    assert not torch.allclose(out[0], out[1])


def test_unconditioned_ignores_z():
    net = _net("none")
    x, k, c = torch.randn(1, 16, 3), torch.tensor([3]), torch.randn(1, 10)
    assert torch.equal(net(x, k, c, torch.zeros(1, 2)), net(x, k, c, torch.ones(1, 2) * 5))


@pytest.mark.numerics
def test_linear_schedule_is_diffusers_linear():
    """"linear" is diffusers' (LeRobot diffusion's) schedule with the same beta_start / beta_end, so that DP and
    PDP share the forward process; a config's beta_end None is the scaled end "linear" checkpoints were saved with."""
    from diffusers import DDIMScheduler

    from lerobot_pdp.configuration_pdp import linear_beta_end

    for K, start, end in ((20, 1e-4, 0.02), (100, 1e-4, 0.02), (20, 5e-4, 0.05)):
        ref = DDIMScheduler(num_train_timesteps=K, beta_schedule="linear", beta_start=start, beta_end=end)
        ours = NoiseSchedule(K, "linear", beta_start=start, beta_end=end)
        torch.testing.assert_close(ours.alphas_cumprod, ref.alphas_cumprod, rtol=1e-6, atol=1e-6)
    assert linear_beta_end(None, 20) == pytest.approx(0.1) and linear_beta_end(0.03, 20) == 0.03
    legacy = NoiseSchedule(20, "linear", beta_end=linear_beta_end(None, 20))
    expected = torch.cumprod(1 - torch.linspace(1e-4, 0.1, 20, dtype=torch.float64), 0).float()
    torch.testing.assert_close(legacy.alphas_cumprod, expected)
    with pytest.raises(ValueError, match="beta_schedule must be"):
        NoiseSchedule(20, "cosine")


@pytest.mark.numerics
def test_schedule_and_ddim():
    s = NoiseSchedule(20)
    assert s.alphas_cumprod.shape == (20,) and bool((s.alphas_cumprod.diff() < 0).all())
    assert s.timesteps(20) == list(range(19, -1, -1))
    assert s.timesteps(5)[0] == 19 and s.timesteps(5)[-1] == 0
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(3, 16, 2, generator=g) * 2 - 1
    eps = torch.randn(x0.shape, generator=g)
    k = torch.tensor([0, 10, 19])
    xk = s.add_noise(x0, eps, k)
    # a perfect noise predictor makes one DDIM step from any k land exactly on x0
    for i, kk in enumerate(k.tolist()):
        out = s.ddim_step(eps[i : i + 1], kk, None, xk[i : i + 1])
        torch.testing.assert_close(out, x0[i : i + 1], atol=1e-4, rtol=1e-4)
    # and the full sampler with an oracle returns x0
    oracle = lambda x, i, kk: (x - s.alphas_cumprod[kk].sqrt() * x0) / (1 - s.alphas_cumprod[kk]).sqrt()  # noqa: E731
    torch.testing.assert_close(s.sample(oracle, torch.randn(x0.shape, generator=g), 10), x0, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize(("mode", "film_hidden_dims"),
                         [("film", (16, 32)), ("film", ()), ("concat", (16, 32)), ("input", (16, 32)), ("none", (16, 32))])
@pytest.mark.numerics
def test_fast_paths_equal_the_reference_forward(mode, film_hidden_dims):
    """Every fast path of fast_inference.py computes ``FiLMUnet1d.forward``: the precomputed modulation with
    PyTorch's or unfolded convolutions, one step for all chunks or one per chunk, latents picked per chunk,
    and the sampler's TorchScript trace. film_hidden_dims=() is the affine FiLM pick-place trains with: the
    stacked z-MLP then has no hidden layer at all."""
    net = _net(mode, film_hidden_dims)
    for m in net.modules():
        if isinstance(m, LatentFiLM):
            torch.nn.init.normal_(m.mlp[-1].weight, std=0.5)
    net.eval()
    x, c, z = torch.randn(3, 16, 3), torch.randn(3, 10), torch.randn(3, 2)
    frozen = FrozenDenoiser(net, 20)
    obs = frozen.observations(c)
    ctx = frozen.context(obs, z)
    fast = FastDenoiser(net, 20)
    steps = [19, 7, 0]
    contexts = fast.contexts(c, z, steps)
    for i, k in enumerate(steps):
        want = net(x, torch.full((3,), k), c, z)
        for unfold in (False, True):
            torch.testing.assert_close(frozen.eps(x, k, ctx, unfold), want, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(fast.run(x, contexts[i]), want, atol=1e-5, rtol=1e-5)  # TorchScript trace
    k = torch.tensor([19, 7, 0])  # one step per chunk, latents picked per chunk (latent fitting)
    zs, rows = torch.randn(2, 2), torch.tensor([1, 0, 1])
    torch.testing.assert_close(frozen.eps(x, k, frozen.context(obs, zs, rows), True), net(x, k, c, zs[rows]),
                               atol=1e-5, rtol=1e-5)
    # the trace (built for batch 3) serves other batch sizes too, e.g. lerobot-eval's --eval.batch_size
    torch.testing.assert_close(fast.run(x[:1], fast.contexts(c[:1], z[:1], steps)[0]),
                               net(x[:1], torch.full((1,), 19), c[:1], z[:1]), atol=1e-5, rtol=1e-5)
    # and a trace built at batch 1 (a single-env rollout) serves a batch of 3 (a vectorised rollout)
    fast1 = FastDenoiser(net, 20)
    fast1.run(x[:1], fast1.contexts(c[:1], z[:1], steps)[0])
    torch.testing.assert_close(fast1.run(x, contexts[0]), net(x, torch.full((3,), 19), c, z), atol=1e-5, rtol=1e-5)


@pytest.mark.numerics
def test_inference_caches_follow_weight_updates_and_pickle():
    net = _net("film").eval()
    fast = FastDenoiser(net, 20)
    x, c, z = torch.randn(1, 16, 3), torch.randn(1, 10), torch.randn(1, 2)
    before = fast.run(x, fast.contexts(c, z, [19, 0])[0])
    with torch.no_grad():  # an optimizer step / load_state_dict changes weights in place
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    after = fast.run(x, fast.contexts(c, z, [19, 0])[0])
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, net(x, torch.tensor([19]), c, z), atol=1e-5, rtol=1e-5)
    clone = pickle.loads(pickle.dumps(fast))  # traces and constants are dropped, rebuilt on demand
    assert clone.net is not net and torch.equal(clone.run(x, clone.contexts(c, z, [19, 0])[0]), after)
    frozen = fast.frozen()
    assert fast.frozen() is frozen  # nothing changed: the same constants (a captured CUDA graph stays valid)
    # parameters replaced by new objects (load_state_dict(assign=True)), even at their old versions: rebuilt
    state = {k: v + 0.05 * torch.randn_like(v) for k, v in net.state_dict().items()}
    net.load_state_dict(state, assign=True)
    assert fast.frozen() is not frozen
    torch.testing.assert_close(fast.run(x, fast.contexts(c, z, [19, 0])[0]), net(x, torch.tensor([19]), c, z),
                               atol=1e-5, rtol=1e-5)


@pytest.mark.numerics
def test_the_latents_modulation_is_reused_only_while_the_latent_stays():
    """A robot acts on one latent for many chunks, so z's FiLM terms are kept between chunks: a latent changed in
    place, a new latent, another batch of latents, and inference mode each give the terms of the z at hand."""
    net = _net("film").eval()
    for m in net.modules():
        if isinstance(m, LatentFiLM):
            torch.nn.init.normal_(m.mlp[-1].weight, std=0.5)
    fast = FastDenoiser(net, 20)
    x, c = torch.randn(1, 16, 3), torch.randn(1, 10)
    z = torch.randn(1, 2)

    def check(z, c=c, x=x):
        torch.testing.assert_close(fast.run(x, fast.contexts(c, z, [7])[0]), net(x, torch.tensor([7] * len(x)), c, z),
                                   atol=1e-5, rtol=1e-5)

    check(z)
    kept = fast._terms
    check(z)
    assert fast._terms is kept  # the same latent: its terms were reused
    z.add_(0.5)  # changed in place (set_latent writes into its buffer)
    check(z)
    check(torch.randn(1, 2))
    check(torch.randn(3, 2), c=torch.randn(3, 10), x=torch.randn(3, 16, 3))  # one latent per chunk
    with torch.inference_mode():
        check(z)
    check(z)


@pytest.mark.numerics
def test_concat_ablation_feeds_the_raw_latent_to_a_linear_map():
    """The paper's concat ablation: z meets a linear map first (no Mish, which would fold distinct negative
    coordinates onto nearly the same value), so every block's condition is affine in z."""
    net = _net("concat", (16, 32)).eval()
    block = net.blocks()[0]
    x, cond = torch.randn(1, 3, 16), torch.randn(1, net.step_embed_dim + 10)
    h = block.conv1(x)

    def modulated(z):  # the block's conditioned features after its first convolution
        act = torch.cat([block.cond_encoder[0](cond), z], dim=-1)
        scale, bias = block.cond_encoder[1](act).unsqueeze(-1).chunk(2, dim=1)
        return scale * h + bias

    z1, z2 = torch.tensor([[-3.0, -1.0]]), torch.tensor([[-6.0, -2.0]])  # Mish(-3) ~ Mish(-6) ~ -0.1
    with torch.no_grad():
        m0, m1, m2 = modulated(torch.zeros(1, 2)), modulated(z1), modulated(z2)
        torch.testing.assert_close(m2 - m0, 2 * (m1 - m0), atol=1e-5, rtol=1e-4)
        # and the network's own forward agrees with that block-level reading
        k = torch.tensor([5])
        out_a = net(torch.randn(1, 16, 3), k, torch.randn(1, 10), z1)
        assert torch.isfinite(out_a).all()
    frozen = FrozenDenoiser(net, 20)
    _, shift = frozen.latent_terms(z1)
    _, shift2 = frozen.latent_terms(z2)
    torch.testing.assert_close(shift2, 2 * shift, atol=1e-5, rtol=1e-4)


def test_input_ablation_appends_the_latent_to_the_denoiser_input_only():
    """The paper's concatenation ablation ("z appended to the denoiser input"): z enters as d_z constant
    channels of the noisy chunk and meets only the first block's convolutions, no block's modulation."""
    net = _net("input").eval()
    first = net.blocks()[0]
    assert first.conv1.block[0].in_channels == 3 + 2 and first.residual.in_channels == 3 + 2
    frozen = FrozenDenoiser(net, 20)
    block_rows = sum(frozen.sizes) - 2
    with torch.no_grad():
        z = torch.tensor([[0.7, -1.3]])
        gain, shift = frozen.latent_terms(z)
        assert gain is None and torch.count_nonzero(shift[:, :block_rows]) == 0
        assert torch.equal(shift[:, block_rows:], z)  # the last modulation rows carry z itself
        # the network reads [A^k | z z ... z]: the first block's conv on that input is what the forward sees
        x, k, c = torch.randn(1, 16, 3), torch.tensor([5]), torch.randn(1, 10)
        seen = {}

        def keep_input(module, inp, out):  # returns None: the output is left as it is
            seen.setdefault("x", inp[0])

        hook = first.conv1.register_forward_hook(keep_input)
        out_a = net(x, k, c, z)
        hook.remove()
        torch.testing.assert_close(seen["x"], torch.cat([x.transpose(1, 2), z[:, :, None].expand(1, 2, 16)], 1))
        assert not torch.allclose(out_a, net(x, k, c, -z))


@pytest.mark.numerics
def test_pdp_ddim_step_is_diffusers_ddim_on_a_self_consistent_grid():
    """PDP's sampler step is diffusers' DDIM step (cosine schedule, x0 clipped to [-1, 1]) with the noise
    re-derived from the clipped x0 (``use_clipped_model_output=True``). Pinned on diffusers' "leading" grid,
    whose steps go to the next grid point (for K = 20, 5 steps: 16, 12, 8, 4, 0). LeRobot's
    ``diffusion`` calls the same scheduler without re-deriving the noise, which differs whenever clipping
    acts: the two policies' samplers are not identical (docs/experiments.md)."""
    from diffusers import DDIMScheduler

    ours = NoiseSchedule(20, "squaredcos_cap_v2", clip_sample=True, clip_sample_range=1.0)
    ref = DDIMScheduler(num_train_timesteps=20, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                        clip_sample_range=1.0, set_alpha_to_one=True, timestep_spacing="leading",
                        prediction_type="epsilon")
    ref.set_timesteps(5)
    grid = ref.timesteps.tolist()
    assert grid == [16, 12, 8, 4, 0]
    g = torch.Generator().manual_seed(0)
    x, eps = torch.randn(4, 16, 2, generator=g) * 1.5, torch.randn(4, 16, 2, generator=g) * 2
    differs = []
    for i, k in enumerate(grid):
        k_prev = grid[i + 1] if i + 1 < len(grid) else None
        step = ours.ddim_step(eps, k, k_prev, x)
        torch.testing.assert_close(step, ref.step(eps, k, x, use_clipped_model_output=True).prev_sample,
                                   atol=2e-6, rtol=1e-5)
        differs.append(float((step - ref.step(eps, k, x).prev_sample).abs().max()))
    assert max(differs) > 0.1  # LeRobot DP's default step is another sampler once clipping acts
    # PDP's own grid is evenly spaced from K - 1 (diffusers' "linspace" points, but diffusers steps from
    # each of them by K // n instead of to the next one)
    assert ours.timesteps(5) == [19, 14, 10, 5, 0]


@pytest.mark.parametrize("spacing", ["leading", "trailing"])
@pytest.mark.parametrize("clipped", [False, True])
@pytest.mark.numerics
def test_pdp_sampler_is_diffusers_ddim_on_diffusers_grids(spacing, clipped):
    """With ``timestep_spacing`` "leading" / "trailing" PDP's whole sampler (grid, step rule, final step)
    is diffusers' DDIM loop, at step counts that divide K and at ones that do not; "leading" without the
    clipped-noise re-derivation is exactly what LeRobot's ``diffusion`` runs, so the benchmark can give both
    methods one sampler."""
    from diffusers import DDIMScheduler

    def denoise(x: torch.Tensor, k: int) -> torch.Tensor:  # any deterministic function of (x, k)
        return torch.tanh(0.7 * x + 0.05 * k) * 1.8

    g = torch.Generator().manual_seed(1)
    noise = torch.randn(3, 16, 2, generator=g) * 1.2
    for n in (1, 3, 5, 7, 10, 20):
        ours = NoiseSchedule(20, "squaredcos_cap_v2", clip_sample=True, clip_sample_range=1.0,
                             timestep_spacing=spacing, use_clipped_model_output=clipped)
        ref = DDIMScheduler(num_train_timesteps=20, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                            clip_sample_range=1.0, set_alpha_to_one=True, timestep_spacing=spacing,
                            prediction_type="epsilon")
        ref.set_timesteps(n)
        assert ours.timesteps(n) == ref.timesteps.tolist()
        x = noise
        for t in ref.timesteps:
            x = ref.step(denoise(x, int(t)), t, x, use_clipped_model_output=clipped).prev_sample
        got = ours.sample(lambda xx, i, k: denoise(xx, k), noise, n)
        torch.testing.assert_close(got, x, atol=3e-6, rtol=1e-5)
    # at n = K every grid visits every step: the three spacings differ only below K
    assert ours.timesteps(20) == list(range(19, -1, -1)) == NoiseSchedule(20).timesteps(20)
    if spacing == "trailing":
        assert ours.timesteps(5) == [19, 15, 11, 7, 3]  # starts from pure noise, unlike "leading"'s 16


def test_sampler_fields_reach_the_policy(synthetic_meta):
    """The default is LeRobot diffusion's DDIM sampler (diffusers' "leading" grid, no clipped-noise rule); the
    fields reach the policy's sampler (checkpoints without them: test_policy.py); a bad spacing is refused."""
    from policies import small_policy

    from lerobot_pdp import PDPConfig

    assert (PDPConfig.timestep_spacing, PDPConfig.use_clipped_model_output) == ("leading", False)
    sched = small_policy(synthetic_meta).model.noise_schedule
    assert sched.timesteps(5) == [16, 12, 8, 4, 0] and not sched.use_clipped_model_output
    sched = small_policy(synthetic_meta, timestep_spacing="even", use_clipped_model_output=True).model.noise_schedule
    assert sched.timesteps(5) == [19, 14, 10, 5, 0] and sched.use_clipped_model_output
    with pytest.raises(ValueError, match="timestep_spacing"):
        PDPConfig(device="cpu", timestep_spacing="linspace")


def test_the_sampler_builds_no_tensor_from_host_data(synthetic_meta):
    """A tensor made from Python data inside the sampler is, on a GPU, a copy from pageable host memory:
    CUDA graph capture refuses it (the sampler then acts eagerly, ~6x slower per chunk) and it waits for the
    GPU. Seen on the CPU as ``aten.lift_fresh`` among the ops the sampler dispatches, eager and compiled path."""
    from policies import small_policy
    from torch.utils._python_dispatch import TorchDispatchMode

    class Ops(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.names: list[str] = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.names.append(str(func))
            return func(*args, **(kwargs or {}))

    p = small_policy(synthetic_meta, "cpu")
    p.eval()
    obs, z = torch.randn(1, p.model.denoiser.obs_cond_dim), torch.randn(1, p.config.latent_dim)
    noise = torch.randn(1, p.config.horizon, p.action_dim)
    n, fast = p.config.num_inference_steps, p.model.fast_denoiser
    steps = p.model.noise_schedule.timesteps(n)  # the grid is built on the host once, before any capture
    fast.frozen()  # weight constants: built before a capture too (PDPModel._generate_graphed)
    prefix = PrefixGuide(torch.zeros_like(noise), torch.linspace(1, 0, p.config.horizon)[None, :, None])
    with torch.no_grad():
        p.model._sample(obs, z, noise, n, prefix)  # builds the CPU trace
    with torch.no_grad(), Ops() as ops:
        fast.contexts(obs, z, steps)  # the GPU sampler's eager part
        p.model._denoise(noise, fast.sample_modulation(obs, z, steps), n)
        p.model._sample(obs, z, noise, n, prefix)  # a real-time chunking prefix: graphed on a GPU too
    assert "aten.addcmul.default" in ops.names and "aten.lerp.Tensor" in ops.names
    assert not [o for o in ops.names if "lift_fresh" in o]


def test_sampler_constants_follow_new_parameter_storage():
    """Weights moved there and back (``.to()``, ``p.data = ...``) keep their parameter objects and versions but
    get new memory: the sampler's constants, which own its captured CUDA graph, are rebuilt, so that the graph is
    captured anew instead of reading freed memory."""
    net = FiLMUnet1d(2, 8, 2, "film", (16, 32))
    fast = FastDenoiser(net, 100)
    before = fast.frozen()
    net.double()
    net.float()
    assert fast.frozen() is not before and fast.frozen() is fast.frozen()


@pytest.mark.numerics
def test_cpu_sampler_matches_a_float64_reference(synthetic_meta):
    """The CPU sampler (precomputed modulation through a TorchScript trace, float32) stays within 2e-5 of the
    same sampler run in float64 over the whole 20-step chain; a float64 copy of a policy samples in float64
    throughout (the GPU test compares its two convolution paths this way). The weights are seeded: over 12
    weight seeds the error was 4e-6 to 2.5e-5, once 1.1e-4, where a predicted x0 sits at the clip bound and
    float32 round-off decides whether it is clipped (seed 0: 8.5e-6)."""
    import copy

    from policies import small_policy

    torch.manual_seed(0)
    p = small_policy(synthetic_meta, "cpu")
    p.eval()
    ref = copy.deepcopy(p.model).double()
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(2, p.model.denoiser.obs_cond_dim, generator=g)
    z = torch.randn(2, p.config.latent_dim, generator=g)
    noise = torch.randn(2, p.config.horizon, p.action_dim, generator=g)
    n = p.config.num_inference_steps
    want = ref._sample(obs.double(), z.double(), noise.double(), n)
    assert want.dtype == torch.float64
    got = p.model._sample(obs, z, noise, n)
    assert got.dtype == torch.float32 and 0 < (got.double() - want).abs().max().item() <= 2e-5


def test_the_training_graphs_key_follows_reassigned_and_moved_tensors(synthetic_meta):
    """The captured training step is keyed by where the model's parameters and buffers live: a buffer
    reassigned (new behaviors in the bank), a parameter frozen or the weights moved give another key (captured
    anew on a GPU), the same model untouched the same one."""
    from policies import small_policy

    from lerobot_pdp.cuda_graphs import TrainGraphs

    model = small_policy(synthetic_meta).model
    graphs = TrainGraphs()
    key = graphs._storage(model)
    assert graphs._storage(model) == key and len(key) == len(list(model.parameters())) + len(list(model.buffers()))
    model.bank.traces = model.bank.traces.clone()
    assert graphs._storage(model) != key
    key = graphs._storage(model)
    next(model.denoiser.parameters()).requires_grad_(False)
    assert graphs._storage(model) != key
    key = graphs._storage(model)
    model.double()
    assert graphs._storage(model) != key


def test_tracing_the_denoiser_hides_only_jits_own_warnings(monkeypatch):
    """The CPU sampler's first chunk traces the denoiser and silences TorchScript's deprecation notices; warnings
    filters are process-wide, so anything else warned meanwhile (a fit in another thread) is still seen."""
    import warnings

    net = FiLMUnet1d(2, 8, 2, "film", (16, 32))
    fast = FastDenoiser(net, 100)
    trace = torch.jit.trace

    def tracing_while_another_thread_warns(*args, **kwargs):
        warnings.warn("a fit's warning, meanwhile", UserWarning, stacklevel=1)
        return trace(*args, **kwargs)

    monkeypatch.setattr(torch.jit, "trace", tracing_while_another_thread_warns)
    context = fast.contexts(torch.randn(1, 8), torch.randn(1, 2), [3])[0]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        fast.run(torch.randn(1, 16, 2), context)
    assert [str(w.message) for w in seen] == ["a fit's warning, meanwhile"]
