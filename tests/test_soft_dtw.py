"""Soft-DTW: values and gradients against brute force, hard DTW, finite differences and each other."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lerobot_pdp.soft_dtw import _soft_dtw_torch_cost, dtw, soft_dtw, soft_dtw_cdist

# float64 values and gradients at 1e-10..1e-12 against brute force and each other: `make test` reruns them
# under other kernel code paths (numba's JIT and ATen's vectorised exp / log follow the CPU)
pytestmark = pytest.mark.numerics

BACKENDS = ["numba", "torch"]


def _smooth(rng: np.random.Generator, *shape: int, scale: float = 0.1) -> np.ndarray:
    """Random-walk trajectories along axis -2: realistic, with many near-tied alignments."""
    return np.cumsum(rng.normal(size=shape), axis=-2) * scale


def _paths(n: int, m: int) -> list[list[tuple[int, int]]]:
    """Every monotone alignment path from (0, 0) to (n - 1, m - 1)."""
    if n == 1 and m == 1:
        return [[(0, 0)]]
    out = []
    for di, dj in ((1, 0), (0, 1), (1, 1)):
        if n - di >= 1 and m - dj >= 1:
            out += [p + [(n - 1, m - 1)] for p in _paths(n - di, m - dj)]
    return out


def _delannoy(n: int, m: int) -> int:
    """Number of alignments of lengths n and m."""
    return sum(math.comb(n - 1, k) * math.comb(m - 1, k) * 2**k for k in range(min(n, m)))


def _brute(D: np.ndarray, gamma: float) -> tuple[float, np.ndarray]:
    """Soft-DTW value and expected alignment matrix by enumerating all alignments."""
    paths = _paths(*D.shape)
    costs = np.array([sum(D[i, j] for i, j in p) for p in paths])
    z = -costs / gamma
    lse = z.max() + np.log(np.exp(z - z.max()).sum())
    probs = np.exp(z - lse)
    E = np.zeros_like(D)
    for p, w in zip(paths, probs, strict=True):
        for i, j in p:
            E[i, j] += w
    return -gamma * lse, E


def _sqdist(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)


# ---------------------------------------------------------------------------------------------------
# Exact references
# ---------------------------------------------------------------------------------------------------
def test_path_enumeration_counts() -> None:
    for n, m in [(1, 1), (1, 4), (3, 3), (4, 3), (4, 4)]:
        assert len(_paths(n, m)) == _delannoy(n, m)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("gamma", [0.1, 1.0])
@pytest.mark.parametrize("n,m", [(1, 3), (3, 1), (2, 2), (3, 4), (4, 4), (4, 2)])
def test_against_brute_force(backend: str, gamma: float, n: int, m: int) -> None:
    rng = np.random.default_rng(n * 10 + m)
    x, y = rng.normal(size=(n, 2)), rng.normal(size=(m, 2))
    val, E = _brute(_sqdist(x, y), gamma)
    xt = torch.tensor(x, requires_grad=True)
    yt = torch.tensor(y, requires_grad=True)
    out = soft_dtw(xt, yt, gamma, backend=backend)
    out.backward()
    assert out.item() == pytest.approx(val, rel=1e-12, abs=1e-12)
    # chain rule of D_ij = |x_i - y_j|^2 applied to dvalue/dD = E
    gx = 2 * (E.sum(1)[:, None] * x - E @ y)
    gy = 2 * (E.sum(0)[:, None] * y - E.T @ x)
    np.testing.assert_allclose(xt.grad.numpy(), gx, atol=1e-12)
    np.testing.assert_allclose(yt.grad.numpy(), gy, atol=1e-12)


@pytest.mark.parametrize("gamma", [0.1, 1.0])
def test_gradient_wrt_cost_is_expected_alignment(gamma: float) -> None:
    """On an arbitrary (non-Euclidean) cost matrix, dvalue/dD is the expected alignment matrix."""
    rng = np.random.default_rng(1)
    D = rng.uniform(0, 2, size=(2, 4, 3))
    Dt = torch.tensor(D, requires_grad=True)
    lens = torch.tensor([4, 3])
    out = _soft_dtw_torch_cost(Dt, lens, torch.tensor([3, 2]), gamma, -1)
    out.sum().backward()
    for b, (n, m) in enumerate([(4, 3), (3, 2)]):
        val, E = _brute(D[b, :n, :m], gamma)
        assert out[b].item() == pytest.approx(val, abs=1e-12)
        G = np.zeros((4, 3))
        G[:n, :m] = E
        np.testing.assert_allclose(Dt.grad[b].numpy(), G, atol=1e-12)


def test_small_gamma_matches_hard_dtw() -> None:
    rng = np.random.default_rng(2)
    for n, m in [(1, 1), (5, 9), (40, 33), (300, 280)]:
        x, y = _smooth(rng, n, 3), _smooth(rng, m, 3)
        hard = dtw(x, y)
        gamma = 1e-5
        soft = soft_dtw(torch.tensor(x), torch.tensor(y), gamma).item()
        # softmin <= min, and softmin >= min - gamma * log(#alignments)
        slack = gamma * math.log(_delannoy(n, m))
        assert hard - slack - 1e-9 <= soft <= hard + 1e-9
    # hard DTW itself against enumeration
    x, y = rng.normal(size=(4, 2)), rng.normal(size=(3, 2))
    D = _sqdist(x, y)
    assert dtw(x, y) == pytest.approx(min(sum(D[i, j] for i, j in p) for p in _paths(4, 3)), abs=1e-12)


# ---------------------------------------------------------------------------------------------------
# Gradients
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("gamma", [0.1, 1.0])
@pytest.mark.parametrize("variant", ["plain", "lengths", "band", "normalize"])
def test_gradcheck(backend: str, gamma: float, variant: str) -> None:
    torch.manual_seed(0)
    x = torch.randn(2, 5, 2, dtype=torch.float64, requires_grad=True)
    y = torch.randn(2, 4, 2, dtype=torch.float64, requires_grad=True)
    kw: dict = {}
    if variant == "lengths":
        kw = {"x_lengths": torch.tensor([5, 3]), "y_lengths": torch.tensor([2, 4])}
    elif variant == "band":
        kw = {"band": 1}
    elif variant == "normalize":
        kw = {"normalize": True}

    def f(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return soft_dtw(a, b, gamma, backend=backend, **kw)

    assert torch.autograd.gradcheck(f, (x, y), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.fixture(scope="module")
def long_pair() -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(3)
    t = np.linspace(0, 4 * np.pi, 300)[:, None]
    x = np.concatenate([np.sin(t), np.cos(0.5 * t)], 1) + _smooth(rng, 300, 2, scale=0.02)
    t2 = np.linspace(0, 4 * np.pi, 320)[:, None] ** 1.05 / (4 * np.pi) ** 0.05
    y = np.concatenate([np.sin(t2), np.cos(0.5 * t2)], 1) + _smooth(rng, 320, 2, scale=0.02)
    return torch.tensor(x), torch.tensor(y)


@pytest.mark.parametrize("backend", BACKENDS)
def test_finite_differences_small_gamma_long(
    long_pair: tuple[torch.Tensor, torch.Tensor], backend: str
) -> None:
    """gamma = 1e-5, T >= 300: where the unnormalised E-matrix recursion breaks down."""
    gamma = 1e-5
    x0, y0 = long_pair
    x = x0.clone().requires_grad_(True)
    y = y0.clone().requires_grad_(True)
    soft_dtw(x, y, gamma, backend=backend).backward()
    rng = np.random.default_rng(4)
    h = 1e-6
    for name, t, g in (("x", x0, x.grad), ("y", y0, y.grad)):
        for flat in rng.choice(t.numel(), size=5, replace=False):
            idx = np.unravel_index(flat, t.shape)
            tp, tm = t.clone(), t.clone()
            tp[idx] += h
            tm[idx] -= h
            if name == "x":
                fp, fm = soft_dtw(tp, y0, gamma).item(), soft_dtw(tm, y0, gamma).item()
            else:
                fp, fm = soft_dtw(x0, tp, gamma).item(), soft_dtw(x0, tm, gamma).item()
            fd = (fp - fm) / (2 * h)
            assert g[idx].item() == pytest.approx(fd, abs=1e-5, rel=1e-4), (name, idx)


def test_float32_matches_float64_small_gamma(long_pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    gamma = 1e-5
    x0, y0 = long_pair
    x64 = x0.clone().requires_grad_(True)
    soft_dtw(x64, y0, gamma).backward()
    for backend in BACKENDS:
        x32 = x0.float().requires_grad_(True)
        y32 = y0.float().requires_grad_(True)
        v32 = soft_dtw(x32, y32, gamma, backend=backend)
        v32.backward()
        assert v32.dtype == torch.float32
        assert torch.isfinite(x32.grad).all() and torch.isfinite(y32.grad).all()
        assert v32.item() == pytest.approx(soft_dtw(x0, y0, gamma).item(), rel=1e-5)
        scale = x64.grad.abs().max().item()
        assert (x32.grad.double() - x64.grad).abs().max().item() <= 1e-2 * scale


# ---------------------------------------------------------------------------------------------------
# Backends, batching, all pairs
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("gamma", [1e-5, 0.1, 1.0])
@pytest.mark.parametrize("band", [None, 2])
def test_torch_path_equals_numba_path(gamma: float, band: int | None) -> None:
    rng = np.random.default_rng(5)
    xs = torch.tensor(_smooth(rng, 4, 30, 3))
    ys = torch.tensor(_smooth(rng, 4, 25, 3))
    kw = {"x_lengths": torch.tensor([30, 12, 7, 30]), "y_lengths": torch.tensor([25, 25, 9, 3]), "band": band}
    res = {}
    for backend in BACKENDS:
        x, y = xs.clone().requires_grad_(True), ys.clone().requires_grad_(True)
        v = soft_dtw(x, y, gamma, backend=backend, **kw)
        v.sum().backward()
        res[backend] = (v.detach(), x.grad, y.grad)
    for a, b in zip(res["numba"], res["torch"], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_cdist_equals_batched_pairwise() -> None:
    rng = np.random.default_rng(6)
    lens = [12, 5, 20, 1, 17, 9]
    seqs = [_smooth(rng, n, 3) for n in lens]
    gamma = 0.1
    C = soft_dtw_cdist(seqs, gamma, band=4)
    N = len(seqs)
    pad = np.zeros((N, max(lens), 3))
    for k, s in enumerate(seqs):
        pad[k, : len(s)] = s
    ii, jj = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    L = torch.tensor(lens)
    ref = soft_dtw(
        torch.tensor(pad[ii]), torch.tensor(pad[jj]), gamma, x_lengths=L[ii], y_lengths=L[jj], band=4
    )
    np.testing.assert_allclose(C, ref.numpy().reshape(N, N), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(C, C.T)
    # same from the padded array + lengths, and with an explicit Y
    np.testing.assert_allclose(soft_dtw_cdist(pad, gamma, lengths=lens, band=4), C, rtol=1e-12, atol=1e-12)
    C2 = soft_dtw_cdist(seqs[:2], gamma, Y=seqs, band=4)
    np.testing.assert_allclose(C2, C[:2], rtol=1e-12, atol=1e-12)
    assert C.dtype == np.float64


def test_cdist_normalized_and_progress() -> None:
    rng = np.random.default_rng(7)
    X = _smooth(rng, 9, 15, 2)
    gamma = 0.5
    Cn = soft_dtw_cdist(X, gamma, normalize=True, progress=True)
    assert np.all(np.diag(Cn) == 0.0)
    np.testing.assert_array_equal(Cn, Cn.T)
    assert (Cn[~np.eye(9, dtype=bool)] > 0).all()  # the divergence is positive for distinct series
    xt = torch.tensor(X)
    ref = soft_dtw(
        xt[:, None].expand(9, 9, 15, 2).reshape(81, 15, 2),
        xt[None].expand(9, 9, 15, 2).reshape(81, 15, 2),
        gamma,
        normalize=True,
    )
    np.testing.assert_allclose(Cn, ref.numpy().reshape(9, 9), atol=1e-12)
    Cxy = soft_dtw_cdist(X[:3], gamma, Y=X[3:], normalize=True)
    np.testing.assert_allclose(Cxy, Cn[:3, 3:], atol=1e-12)


def test_normalize_zero_on_identical_and_unbatched_scalar() -> None:
    x = torch.randn(7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0), requires_grad=True)
    v = soft_dtw(x, x, 1.0, normalize=True)
    assert v.dim() == 0 and v.item() == 0.0
    v.backward()
    assert torch.allclose(x.grad, torch.zeros_like(x), atol=1e-12)


# ---------------------------------------------------------------------------------------------------
# Variable lengths, padding, bands
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", BACKENDS)
def test_padding_is_ignored_exactly(backend: str) -> None:
    rng = np.random.default_rng(8)
    x0, y0 = torch.tensor(_smooth(rng, 11, 3)), torch.tensor(_smooth(rng, 6, 3))
    xp = torch.full((2, 15, 3), float("nan"), dtype=torch.float64)
    yp = torch.full((2, 9, 3), 1e30, dtype=torch.float64)
    xp[0, :11], yp[0, :6] = x0, y0
    xp[1], yp[1] = 0.0, 0.0
    xp, yp = xp.requires_grad_(True), yp.requires_grad_(True)
    for gamma in (1e-5, 0.3):
        xp.grad = yp.grad = None
        v = soft_dtw(
            xp, yp, gamma, x_lengths=torch.tensor([11, 15]), y_lengths=torch.tensor([6, 9]), backend=backend
        )
        v.sum().backward()
        x1, y1 = x0.clone().requires_grad_(True), y0.clone().requires_grad_(True)
        ref = soft_dtw(x1, y1, gamma, backend=backend)
        ref.backward()
        assert v[0].item() == pytest.approx(ref.item(), abs=1e-12)
        assert torch.isfinite(xp.grad).all() and torch.isfinite(yp.grad).all()
        torch.testing.assert_close(xp.grad[0, :11], x1.grad, rtol=0, atol=1e-12)
        torch.testing.assert_close(yp.grad[0, :6], y1.grad, rtol=0, atol=1e-12)
        assert (xp.grad[0, 11:] == 0).all() and (yp.grad[0, 6:] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_band_semantics(backend: str) -> None:
    rng = np.random.default_rng(9)
    x, y = torch.tensor(_smooth(rng, 12, 2)), torch.tensor(_smooth(rng, 12, 2))
    # band 0, equal lengths: only the diagonal path (Euclidean), any gamma
    v0 = soft_dtw(x, y, 0.7, band=0, backend=backend).item()
    assert v0 == pytest.approx(((x - y) ** 2).sum().item(), rel=1e-12)
    # band >= length: no constraint
    for g in (1e-5, 0.7):
        assert soft_dtw(x, y, g, band=12, backend=backend).item() == pytest.approx(
            soft_dtw(x, y, g, backend=backend).item(), rel=1e-12
        )
    # narrowing the band can only remove alignments: hard value grows monotonically
    vals = [soft_dtw(x, y, 1e-5, band=b, backend=backend).item() for b in (0, 1, 2, 4, 12)]
    assert all(a >= b - 1e-9 for a, b in zip(vals, vals[1:], strict=False))


@pytest.mark.parametrize("backend", BACKENDS)
def test_narrow_band_unequal_lengths(backend: str) -> None:
    """band >= 1 is feasible for any lengths (band measured along the shorter series); band 0 raises."""
    rng = np.random.default_rng(10)
    for n, m in [(40, 6), (6, 40), (2, 50), (1, 9)]:
        x = torch.tensor(_smooth(rng, 1, n, 2), requires_grad=True)
        y = torch.tensor(_smooth(rng, 1, m, 2), requires_grad=True)
        v = soft_dtw(x, y, 1e-5, band=1, backend=backend)
        v.sum().backward()
        assert v.item() < 1e100 and torch.isfinite(v).all()
        assert torch.isfinite(x.grad).all() and torch.isfinite(y.grad).all()
        assert v.item() >= soft_dtw(x, y, 1e-5).item() - 1e-9
    with pytest.raises(ValueError, match=r"x length 40, y length 6"):
        soft_dtw(torch.zeros(40, 2), torch.zeros(6, 2), band=0, backend=backend)
    with pytest.raises(ValueError, match="band"):
        soft_dtw_cdist([np.zeros((4, 2)), np.zeros((5, 2))], band=0)
    soft_dtw(torch.zeros(1, 2), torch.zeros(6, 2), band=0, backend=backend)  # single step: always feasible


# ---------------------------------------------------------------------------------------------------
# Errors and devices
# ---------------------------------------------------------------------------------------------------
def test_bad_inputs() -> None:
    x, y = torch.zeros(2, 5, 3), torch.zeros(2, 4, 3)
    for g in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="gamma"):
            soft_dtw(x, y, g)
        with pytest.raises(ValueError, match="gamma"):
            soft_dtw_cdist(np.zeros((2, 3, 1)), g)
    with pytest.raises(ValueError, match=r"feature dims differ.*\(2, 5, 3\).*\(2, 4, 2\)"):
        soft_dtw(x, torch.zeros(2, 4, 2))
    with pytest.raises(ValueError, match="batch sizes differ"):
        soft_dtw(x, torch.zeros(3, 4, 3))
    bad = x.clone()
    bad[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match=r"^y \(shape \(2, 5, 3\)\) contains NaN/inf at \[1, 2\]"):
        soft_dtw(torch.zeros(2, 1, 3), bad)
    with pytest.raises(ValueError, match=r"^x \(shape"):
        soft_dtw(bad, y)
    with pytest.raises(ValueError, match=r"x_lengths must lie in \[1, 5\]"):
        soft_dtw(x, y, x_lengths=torch.tensor([0, 5]))
    with pytest.raises(ValueError, match="band"):
        soft_dtw(x, y, band=-1)
    with pytest.raises(ValueError, match=r"X\[1\] \(shape \(4, 2\)\) contains NaN/inf at step 3"):
        soft_dtw_cdist([np.zeros((3, 2)), np.array([[0, 0], [0, 0], [0, 0], [np.inf, 0]])])
    with pytest.raises(ValueError, match="same d"):
        dtw(np.zeros((3, 2)), np.zeros((3, 3)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(11)
    x = torch.tensor(_smooth(rng, 3, 20, 2), requires_grad=True)
    y = torch.tensor(_smooth(rng, 3, 18, 2))
    v = soft_dtw(x, y, 0.01)
    v.sum().backward()
    xc = x.detach().cuda().float().requires_grad_(True)
    vc = soft_dtw(xc, y.cuda().float(), 0.01)
    vc.sum().backward()
    assert vc.device.type == "cuda"
    torch.testing.assert_close(vc.cpu().double(), v.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(xc.grad.cpu().double(), x.grad, rtol=1e-3, atol=1e-4)


def test_parallel_kernels_leave_torchs_thread_count_alone() -> None:
    """numba's OpenMP layer shares PyTorch's libgomp: a parallel soft-DTW matrix (computed at the start of
    ``lerobot-train`` when the trace cache is cold) must not raise torch's thread count for the training
    that follows (it did: 1 -> 2, ~10x slower steps beside other jobs on 2 cores)."""
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rng = np.random.default_rng(0)
        traces = [rng.random((100, 2)) for _ in range(40)]  # 780 pairs x 1e4 cells: the parallel path
        soft_dtw_cdist(traces, 0.1)
        soft_dtw(torch.tensor(np.stack(traces[:30])), torch.tensor(np.stack(traces[10:])), gamma=0.1)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(prev)
