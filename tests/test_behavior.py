"""Behavior traces, kappa and the trajectory VAE."""

import numpy as np
import pytest
import torch

from lerobot_pdp.behavior import (
    TrajectoryVAE,
    build_behavior_traces,
    choose_kappa,
    gripper_segments,
    normalize_trace,
    prior_mean_distance,
    read_episodes,
    resample,
)


def test_resample_keeps_endpoints_and_shape():
    x = np.stack([np.linspace(0, 1, 37), np.linspace(2, 0, 37)], 1)
    r = resample(x, 64)
    assert r.shape == (64, 2)
    np.testing.assert_allclose(r[0], x[0])
    np.testing.assert_allclose(r[-1], x[-1])
    np.testing.assert_allclose(resample(x[:1], 5), np.repeat(x[:1], 5, 0))


def test_normalize_trace():
    x = np.array([[1.0, 1.0], [2.0, 1.0], [3.0, 1.0]])
    np.testing.assert_allclose(normalize_trace(x, "start")[0], [0, 0])
    np.testing.assert_allclose(normalize_trace(x, "endpoints")[-1], [1, 0])


def test_gripper_segments_split_and_merge_chatter():
    a = np.zeros((20, 4))
    a[8:15, 3] = 1.0  # close at 8, open at 15
    assert gripper_segments(a, 3, 0.0) == [(0, 8), (8, 15), (15, 20)]
    a[10, 3] = -1.0  # one-frame chatter is merged
    assert gripper_segments(a, 3, 0.0, min_length=2) == [(0, 8), (8, 15), (15, 20)]


def test_gripper_segments_too_short_first_or_last_run_joins_its_neighbour():
    """An episode that ends one frame after the gripper opens has no "release" behavior to learn."""
    a = -np.ones((20, 4))
    a[8:19, 3] = 1.0  # close at 8, open only on the final frame
    assert gripper_segments(a, 3, 0.0) == [(0, 8), (8, 20)]
    assert gripper_segments(a, 3, 0.0, min_length=1) == [(0, 8), (8, 19), (19, 20)]
    a[0, 3] = 1.0  # a one-frame close on the first frame
    assert gripper_segments(a, 3, 0.0) == [(0, 8), (8, 20)]
    a[:, 3] = 1.0
    assert gripper_segments(a[:1], 3, 0.0) == [(0, 1)]  # shorter than min_length as a whole: one phase


def test_phases_asked_for_and_never_found_are_refused():
    """A real gripper recorded 0..100 never crosses the default threshold 0: no phases, which training said nothing
    of (one latent per episode where the user asked for one per phase)."""
    a = np.zeros((20, 4))
    a[8:15, 3] = 80.0  # closed 80, open 0
    episodes = {0: {"observation.state": np.zeros((20, 2)), "action": a + 5.0, "task": "pick"}}
    with pytest.raises(ValueError, match=r"segment_gripper_dim=3: no episode's gripper command \(action\[3\], values "
                                         r"in \[5, 85\]\) crosses segment_gripper_threshold=0, .*between the gripper's "
                                         r"open and closed values"):
        build_behavior_traces(episodes, "observation.state", None, 8, "none", 3, 0.0)
    assert len(build_behavior_traces(episodes, "observation.state", None, 8, "none", 3, 40.0).traces) == 3


def test_prior_mean_distance_matches_monte_carlo():
    rng = np.random.default_rng(0)
    for d in (1, 2, 5):
        a, b = rng.normal(size=(200000, d)), rng.normal(size=(200000, d))
        assert prior_mean_distance(d) == pytest.approx(np.linalg.norm(a - b, axis=1).mean(), rel=0.01)


def test_choose_kappa_scales_mean_distance_to_prior():
    d = np.array([[0, 2.0, 4.0], [2.0, 0, 6.0], [4.0, 6.0, 0]])
    k = choose_kappa(d, 2)
    assert k * 4.0 == pytest.approx(prior_mean_distance(2))


def test_read_episodes_and_traces(synthetic_dataset):
    eps = read_episodes(synthetic_dataset, ["observation.state", "action"])
    assert len(eps) == 40
    assert eps[3]["task"] == "mode 3: right-wide"
    b = build_behavior_traces(eps, "observation.state", None, 32, "none")
    assert b.traces.shape == (40, 32, 2)
    assert sorted(set(b.mode.tolist())) == [0, 1, 2, 3]
    assert b.mode_names[1] == "left-wide"
    np.testing.assert_array_equal(b.start, 0)
    assert b.global_start[1] == len(eps[0]["action"])


def test_one_mode_id_with_two_names_warns_naming_both(synthetic_dataset, caplog):
    """Two recordings merged, each labelled from mode 0: their episodes train as one mode, which is said."""
    eps = read_episodes(synthetic_dataset, ["observation.state", "action"], [0, 4, 8])
    eps[8]["task"] = "mode 0: pick-left"
    with caplog.at_level("WARNING", logger="lerobot_pdp.behavior"):
        b = build_behavior_traces(eps, "observation.state", None, 8, "none")
    assert "mode 0 has 2 names: 'left-tight' (episodes [0, 4]); 'pick-left' (episodes [8]); PDP trains them as one " \
           "mode named 'left-tight'" in caplog.text
    assert b.mode.tolist() == [0, 0, 0]
    caplog.clear()
    with caplog.at_level("WARNING", logger="lerobot_pdp.behavior"):
        build_behavior_traces(read_episodes(synthetic_dataset, ["observation.state", "action"], [0, 4]),
                              "observation.state", None, 8, "none")
    assert "names" not in caplog.text


def test_read_episodes_reads_only_the_episodes_asked_for(synthetic_dataset):
    """The episode filter is pushed into the parquet read: the same arrays as a full read, nothing else; an
    unknown column is refused naming the file and the columns it has."""
    full = read_episodes(synthetic_dataset, ["observation.state", "action"])
    some = read_episodes(synthetic_dataset, ["observation.state", "action"], [3, 17])
    assert sorted(some) == [3, 17] and read_episodes(synthetic_dataset, ["action"], [10**6]) == {}
    for ep in (3, 17):
        for key in ("observation.state", "action"):
            np.testing.assert_array_equal(some[ep][key], full[ep][key])
        assert (some[ep]["task"], some[ep]["from_index"]) == (full[ep]["task"], full[ep]["from_index"])
    with pytest.raises(KeyError, match=r"\.parquet: dataset has no column\(s\) \['observation.nope'\]; columns are .*action"):
        read_episodes(synthetic_dataset, ["observation.nope"], [3])


def test_nonfinite_state_names_episode():
    eps = {7: {"observation.state": np.array([[0.0, 0.0], [np.nan, 1.0], [1.0, 1.0]]), "task": ""}}
    with pytest.raises(ValueError, match=r"episode 7: 'observation.state' has non-finite values \(first at frame 1"):
        build_behavior_traces(eps, "observation.state", None, 8, "none")


def test_short_episode_is_rejected():
    eps = {2: {"observation.state": np.zeros((1, 2)), "task": ""}, 3: {"observation.state": np.zeros((1, 2)), "task": ""}}
    with pytest.raises(ValueError, match=r"episode 2 has 1 frames \(dataset data/x\); PDP needs at least 2 .*Episodes "
                                         r"this short: \[2, 3\]: leave them out \(--dataset.episodes .* "
                                         r"--policy.n_obs_steps=1"):
        build_behavior_traces(eps, "observation.state", None, 8, "none", min_length=2, source="dataset data/x")


def test_summed_rec_is_the_mean_times_a_traces_elements():
    """The paper's L_rec sums each trace's squared error; the default averages it (L x D times smaller), and
    the other terms are the same either way."""
    vae = TrajectoryVAE(16, 3, 2, (32,))
    x = torch.randn(8, 16, 3)
    vae.set_trace_stats(x)
    dx = torch.rand(8, 8)
    out = {}
    for reduction in ("mean", "sum"):
        torch.manual_seed(0)  # the same reparameterisation noise
        out[reduction] = vae.loss(x, dx + dx.T, 1.0, 1e-3, 1.0, reduction)[1]
    assert torch.allclose(out["sum"]["embed_rec"], out["mean"]["embed_rec"] * 16 * 3, rtol=1e-5)
    for term in ("embed_kl", "embed_geo"):
        assert torch.equal(out["sum"][term], out["mean"][term])


def test_vae_geometry_alignment_orders_latents_like_traces():
    """Four clusters of 1-D offsets: after training, latent distances follow trace distances."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    offsets = np.repeat([-2.0, -1.0, 1.0, 2.0], 8) + rng.normal(0, 0.05, 32)
    t = np.linspace(0, 1, 16)
    traces = np.stack([np.stack([t, off * np.sin(np.pi * t)], 1) for off in offsets])
    dist = np.abs(offsets[:, None] - offsets[None, :]) * 10
    kappa = choose_kappa(dist, 2)
    vae = TrajectoryVAE(16, 2, 2, (64, 64))
    x = torch.tensor(traces, dtype=torch.float32)
    vae.set_trace_stats(x)
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)
    dx = torch.tensor(dist, dtype=torch.float32)
    for _ in range(400):
        loss, info = vae.loss(x, dx, kappa, 1e-3, 1.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    mu = vae.encode(x)[0].detach().numpy()
    dz = np.linalg.norm(mu[:, None] - mu[None], axis=-1)
    iu = np.triu_indices(32, 1)
    corr = np.corrcoef(dz[iu], kappa * dist[iu])[0, 1]
    assert corr > 0.95, corr
    assert info["embed_geo"] < 0.1
