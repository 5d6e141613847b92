"""Demonstration windows match LeRobotDataset's training windows; fitting touches only z."""

import math

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_pdp.chunk_windows import episode_windows
from lerobot_pdp.denoiser import FiLMUnet1d, LatentFiLM, NoiseSchedule
from lerobot_pdp.episodes import read_episodes
from lerobot_pdp.fast_inference import FrozenDenoiser
from lerobot_pdp.latent_fitting import (
    _spread_steps,
    demonstration_error,
    fit_chunk_noise,
    fit_latent,
    fit_loss,
    fit_loss_and_grad_fd,
    select_code,
)


def test_windows_equal_lerobot_dataset_windows(synthetic_dataset):
    n_obs, horizon = 2, 8
    ds = LeRobotDataset("local/synthetic", root=synthetic_dataset, delta_timestamps={
        "observation.state": [i / 10 for i in range(1 - n_obs, 1)],
        "action": [i / 10 for i in range(1 - n_obs, 1 - n_obs + horizon)],
    })
    ep = read_episodes(synthetic_dataset, ["observation.state", "action"], [1])[1]
    norm = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in ep.items() if k in ("observation.state", "action")}
    w = episode_windows(norm, n_obs, horizon, "observation.state", None, [(0, len(ep["action"]))])
    start = ep["from_index"]
    T = len(ep["action"])
    for t in (0, 1, T // 2, T - 3, T - 1):
        item = ds[start + t]
        torch.testing.assert_close(w.actions[t], item["action"])
        torch.testing.assert_close(w.is_pad[t], item["action_is_pad"])
        torch.testing.assert_close(w.obs_cond[t], item["observation.state"].flatten())


@pytest.mark.parametrize("gradient", ["autograd", "finite_difference"])
@pytest.mark.numerics
def test_fit_changes_only_z_and_reduces_loss(gradient):
    torch.manual_seed(0)
    net = FiLMUnet1d(2, 4, 2, "film", down_dims=(16, 32))
    for m in net.modules():  # make z matter
        if m.__class__.__name__ == "LatentFiLM":
            torch.nn.init.normal_(m.mlp[-1].weight, std=0.3)
    sched = NoiseSchedule(20)
    T = 40
    norm = {"observation.state": torch.randn(T, 2), "action": torch.rand(T, 2) * 2 - 1}
    w = episode_windows(norm, 2, 16, "observation.state", None, [(0, 20), (20, T)])
    before = {k: v.clone() for k, v in net.state_dict().items()}
    res = fit_latent(net, sched, w, torch.zeros(2, 2), steps=60, lr=0.05, lam=1e-3, batch_size=32, seed=0,
                     gradient=gradient)
    for k, v in net.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert all(p.grad is None for p in net.parameters())
    assert res.z.shape == (2, 2) and not torch.equal(res.z, res.z_init)
    assert np.mean(res.losses[-10:]) < np.mean(res.losses[:10])


def _two_phase_setup(mode: str):
    """A small U-Net whose FiLM output layer is non-zero (so z matters) and a 30-frame, two-phase demo."""
    torch.manual_seed(0)
    net = FiLMUnet1d(2, 4, 2, mode, down_dims=(16, 32))
    for m in net.modules():
        if isinstance(m, LatentFiLM):
            torch.nn.init.normal_(m.mlp[-1].weight, std=0.3)
    T = 30
    norm = {"observation.state": torch.randn(T, 2), "action": torch.rand(T, 2) * 2 - 1}
    return net, NoiseSchedule(20), episode_windows(norm, 2, 16, "observation.state", None, [(0, 12), (12, T)]), T


@pytest.mark.parametrize("mode", ["film", "concat", "input", "none"])
@pytest.mark.numerics
def test_fit_loss_on_precomputed_modulations_equals_the_training_forward(mode):
    """fit_loss runs the denoiser from cached step/observation modulations; the maths must be forward's."""
    net, sched, w, T = _two_phase_setup(mode)
    z = torch.randn(2, 2, requires_grad=True)
    idx = torch.arange(0, T, 3)
    got = fit_loss(net, sched, w, z, idx, 1, 1e-3, torch.Generator().manual_seed(5))
    # the same draws, through the plain training forward
    g = torch.Generator().manual_seed(5)
    eps = torch.randn(w.actions[idx].shape, generator=g)
    k = torch.randint(0, 20, (len(idx),), generator=g)
    seg = w.segment[idx]
    pred = net(sched.add_noise(w.actions[idx], eps, k), k, w.obs_cond[idx], z[seg])
    mask = (~w.is_pad[idx]).unsqueeze(-1).float()
    per = ((pred - eps) ** 2 * mask).sum((1, 2)) / (mask.sum((1, 2)) * 2)
    want = sum(per[seg == m].mean() for m in (0, 1)) + 1e-3 * z.pow(2).sum()
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    if mode != "none":  # and its gradient reaches z
        (g_got,) = torch.autograd.grad(got, z)
        (g_want,) = torch.autograd.grad(want, z)
        torch.testing.assert_close(g_got, g_want, atol=1e-5, rtol=1e-4)


@pytest.mark.numerics
def test_finite_difference_gradient_matches_autograd_on_the_same_draws():
    """Forward differences over z (all phases at once) agree with the backward pass on the same noise."""
    net, sched, w, T = _two_phase_setup("film")
    frozen = FrozenDenoiser(net, 20)
    obs = frozen.observations(w.obs_cond)
    idx = torch.arange(0, T, 2)
    for trial in range(3):
        z = torch.randn(2, 2)
        zg = z.clone().requires_grad_(True)
        loss = fit_loss(frozen, sched, w, zg, idx, 1, 1e-2, torch.Generator().manual_seed(trial), obs)
        (want,) = torch.autograd.grad(loss, zg)
        fd_loss, got = fit_loss_and_grad_fd(frozen, sched, w, z, idx, 1, 1e-2, torch.Generator().manual_seed(trial),
                                            obs)
        torch.testing.assert_close(fd_loss, loss.detach())
        assert float((got - want).norm() / want.norm()) < 0.02, (got, want)
    with pytest.raises(ValueError, match="gradient must be one of"):
        fit_latent(net, sched, w, torch.zeros(2, 2), steps=1, lr=0.05, lam=0.0, batch_size=4, gradient="exact")


@pytest.mark.numerics
def test_plain_gradient_steps_are_the_papers_update_and_return_the_last_iterate():
    """``optimizer="gradient"``: z <- z - lr * grad on each step's draws (paper Alg. 3), the last z returned (Adam's
    result is the mean of its last iterates)."""
    from lerobot_pdp.latent_fitting import _stratified_batch, frozen_denoiser

    net, sched, w, T = _two_phase_setup("film")
    z0, lr, lam = torch.randn(2, 2), 0.5, 1e-2
    frozen = frozen_denoiser(net, sched)
    obs = frozen.observations(w.obs_cond)
    z, g = z0.clone(), torch.Generator().manual_seed(3)
    for _ in range(2):  # the fit's own draws, in its order
        idx = _stratified_batch(w.segment, w.n_segments, 8, g)
        zg = z.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(fit_loss(frozen, sched, w, zg, idx, 1, lam, g, obs), zg)
        z = z - lr * grad
    res = fit_latent(net, sched, w, z0, steps=2, lr=lr, lam=lam, batch_size=8, seed=3, gradient="autograd",
                     optimizer="gradient")
    torch.testing.assert_close(res.z, z)
    with pytest.raises(ValueError, match="optimizer must be 'adam' or 'gradient'"):
        fit_latent(net, sched, w, z0, steps=1, lr=lr, lam=lam, batch_size=8, optimizer="sgd")


def _learned_setup():
    """:func:`_two_phase_setup` after 150 denoising steps on its demonstration at z = 0 (an untrained
    denoiser's chunks are its random outputs clipped, which neither the step nor the noise changes much)."""
    net, sched, w, T = _two_phase_setup("film")
    z = torch.zeros(2, 2)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(150):
        idx = torch.randint(0, T, (32,), generator=g)
        eps = torch.randn(w.actions[idx].shape, generator=g)
        k = torch.randint(0, 20, (32,), generator=g)
        pred = net(sched.add_noise(w.actions[idx], eps, k), k, w.obs_cond[idx], z[w.segment[idx]])
        opt.zero_grad()
        (pred - eps).pow(2).mean().backward()
        opt.step()
    net.eval()
    net.zero_grad(set_to_none=True)
    return net, sched, w, T, z


def test_spread_steps_cover_every_stratum_once_and_spread_each_window():
    """The fit report's diffusion steps: n draws over n equal strata of [0, T), one each; each window's draws
    in distinct coarse strata (round-major layout, as ``idx.repeat(draws)``)."""
    g = torch.Generator().manual_seed(0)
    for windows, draws, T in ((7, 3, 105), (50, 2, 100), (3, 5, 1500), (130, 1, 100)):
        k = _spread_steps(windows, draws, T, g)
        n = windows * draws
        assert k.shape == (n,) and k.dtype == torch.long and 0 <= int(k.min()) and int(k.max()) < T
        if n <= T:  # T / n is a whole number here: stratum s is [s T/n, (s+1) T/n)
            assert sorted((k * n // T).tolist()) == list(range(n))
        rounds = (k * draws // T).view(draws, windows)  # row j: every window's j-th draw
        assert torch.equal(rounds, torch.arange(draws)[:, None].expand(draws, windows))


@pytest.mark.numerics
def test_demonstration_error_spread_steps_keep_the_mean_with_less_noise():
    """Stratified steps estimate the same L_fit as uniform ones (many draws agree) and, once the denoiser has
    learned the demonstration (its error then depends mostly on the step), vary much less over seeds."""
    net, sched, w, T, z = _learned_setup()
    spread = demonstration_error(net, sched, w, z, chunks=T * 200, seed=1)
    uniform = demonstration_error(net, sched, w, z, chunks=T * 200, seed=1, spread_steps=False)
    assert spread == pytest.approx(uniform, rel=0.03)
    small = [np.std([demonstration_error(net, sched, w, z, chunks=T * 2, seed=s, spread_steps=f) for s in range(30)])
             for f in (True, False)]
    assert small[0] < 0.7 * small[1], small


@pytest.mark.numerics
def test_chunk_noises_make_the_sampler_reproduce_the_demonstration():
    """fit_chunk_noise: the DDIM chains from the fitted noises (under each phase's z) come closer to the
    demonstration's chunks than from the noises it started at; no weight is touched."""
    net, sched, w, T, z = _learned_setup()
    z = z + torch.tensor([[0.3, -0.2], [-0.1, 0.4]])  # one latent per phase, off the one it learned at
    before = {k: v.clone() for k, v in net.state_dict().items()}

    def error(noise: torch.Tensor) -> float:
        x = noise[torch.arange(T) // 4]
        with torch.no_grad():
            for k, k_prev in sched.steps(5):
                x = sched.ddim_step(net(x, torch.full((T,), k), w.obs_cond, z[w.segment]), k, k_prev, x)
        mask = (~w.is_pad).unsqueeze(-1).float()
        return float(((x - w.actions).pow(2) * mask).sum() / (mask.sum() * 2))

    start = fit_chunk_noise(net, sched, w, z, 4, 5, steps=0, seed=3)
    fitted = fit_chunk_noise(net, sched, w, z, 4, 5, steps=100, lr=0.05, seed=3)
    assert start.shape == fitted.shape == (math.ceil(T / 4), 16, 2)
    assert error(fitted) < 0.7 * error(start), (error(fitted), error(start))
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    assert all(q.grad is None for q in net.parameters())


@pytest.mark.numerics
def test_discrete_latent_adapts_by_choosing_the_best_code_per_phase():
    """The one-hot ablation picks one of its codes per phase (no interpolation): every code is scored on the
    same windows and noise, so scoring them one at a time gives the same numbers, and the pick is the minimum."""
    net, sched, w, T = _two_phase_setup("film")
    codes = torch.eye(2)
    chosen, mean = select_code(net, sched, w, codes, batches=4, batch_size=8, seed=3)
    assert mean.shape == (2, 2) and chosen.shape == (2, 2)
    assert torch.equal(chosen, codes[mean.argmin(0)])  # per phase, a whole code: one-hot rows
    alone = torch.cat([select_code(net, sched, w, codes[c:c + 1], batches=4, batch_size=8, seed=3)[1]
                       for c in range(2)])
    torch.testing.assert_close(alone, mean)
    assert not torch.equal(mean[0], mean[1])  # the codes do modulate this net
    # with the sampled-chunk objective (fit_objective="sample") the codes are scored by fit_loss's sample error
    chosen_s, mean_s = select_code(net, sched, w, codes, batches=4, batch_size=8, seed=3, sample_steps=3)
    alone_s = torch.cat([select_code(net, sched, w, codes[c:c + 1], batches=4, batch_size=8, seed=3,
                                     sample_steps=3)[1] for c in range(2)])
    torch.testing.assert_close(alone_s, mean_s)
    assert not torch.allclose(mean_s, mean) and torch.equal(chosen_s, codes[mean_s.argmin(0)])


def test_onehot_policy_fit_returns_one_of_its_codes(synthetic_meta):
    from policies import small_policy

    p = small_policy(synthetic_meta, latent_type="onehot")
    for m in p.model.denoiser.modules():  # FiLM output layers start at zero: give the codes an effect
        if isinstance(m, LatentFiLM):
            torch.nn.init.normal_(m.mlp[-1].weight, std=0.3)
    res = p.fit_latent((synthetic_meta.root, 5), steps=3)
    assert res.z.shape == (4,) and sorted(res.z.tolist()) == [0.0, 0.0, 0.0, 1.0]
    assert torch.equal(p.active_latent[0], res.z) and len(res.losses) == 1


@pytest.mark.parametrize("mode", ["film", "concat", "input"])
@pytest.mark.numerics
def test_sample_objective_is_the_error_of_the_policy_sampler(mode):
    """fit_objective="sample": the fitted quantity is the error of the chunk the network samples with the
    shared sampler (NoiseSchedule.sample over the plain forward), per phase, plus lambda|z|^2, and its
    gradient is that of the plain computation."""
    net, sched, w, T = _two_phase_setup(mode)
    z = torch.randn(2, 2, requires_grad=True)
    idx = torch.arange(0, T, 3)
    got = fit_loss(net, sched, w, z, idx, 1, 1e-3, torch.Generator().manual_seed(5), sample_steps=4)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(w.actions[idx].shape, generator=g)
    seg = w.segment[idx]
    sampled = sched.sample(lambda xx, i, k: net(xx, torch.full((len(idx),), k), w.obs_cond[idx], z[seg]), x, 4)
    mask = (~w.is_pad[idx]).unsqueeze(-1).float()
    per = ((sampled - w.actions[idx]) ** 2 * mask).sum((1, 2)) / (mask.sum((1, 2)) * 2)
    want = sum(per[seg == m].mean() for m in (0, 1)) + 1e-3 * z.pow(2).sum()
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    (g_got,) = torch.autograd.grad(got, z, retain_graph=True)
    (g_want,) = torch.autograd.grad(want, z)
    # looser than the loss: float round-off decides whether an x0 right at the clip bound is clipped
    torch.testing.assert_close(g_got, g_want, atol=1e-3, rtol=1e-2)
    # "auto" takes the backward pass here: the clipped x0 puts kinks into this loss, where one-sided
    # differences are off by far more than on the smooth noise-prediction loss
    res = fit_latent(net, sched, w, torch.zeros(2, 2), steps=3, lr=0.05, lam=1e-3, batch_size=16, seed=0,
                     sample_steps=4)
    fd = fit_latent(net, sched, w, torch.zeros(2, 2), steps=3, lr=0.05, lam=1e-3, batch_size=16, seed=0,
                    sample_steps=4, gradient="finite_difference")
    auto = fit_latent(net, sched, w, torch.zeros(2, 2), steps=3, lr=0.05, lam=1e-3, batch_size=16, seed=0,
                      sample_steps=4, gradient="autograd")
    assert res.losses == auto.losses and fd.losses[0] == pytest.approx(auto.losses[0], rel=1e-5)


def test_policy_fit_objective_sample(synthetic_meta):
    """PDPPolicy.fit_latent(objective="sample") fits on the policy's own sampler (config.fit_objective the
    default); a wrong objective is refused."""
    from policies import small_policy

    p = small_policy(synthetic_meta, num_inference_steps=3)
    res = p.fit_latent((synthetic_meta.root, 5), steps=4, objective="sample")
    assert res.z.shape == (p.config.latent_dim,) and len(res.losses) == 4 and np.isfinite(res.losses).all()
    p.config.fit_objective = "sample"
    again = p.fit_latent((synthetic_meta.root, 5), steps=4)
    torch.testing.assert_close(again.z, res.z)
    with pytest.raises(ValueError, match="objective must be"):
        p.fit_latent((synthetic_meta.root, 5), steps=1, objective="trajectory")
