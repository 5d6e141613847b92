"""Modes without labels: clustering the training latents recovers the demonstrated routes."""

import logging

import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_policy
from sklearn.metrics import adjusted_rand_score

from lerobot_pdp import PDPConfig
from lerobot_pdp.modes import cluster_episodes


@pytest.fixture(scope="module")
def embedded(synthetic_meta):
    """PDP on the synthetic 4-mode dataset with its trajectory VAE trained (L_embed only: seconds)."""
    torch.manual_seed(0)
    p = make_policy(PDPConfig(device="cpu", push_to_hub=False, down_dims=(16, 32)), ds_meta=synthetic_meta)
    opt = torch.optim.Adam(p.model.vae.parameters(), lr=1e-3)
    for _ in range(400):
        loss, _ = p.model.embedding_loss("cpu")
        opt.zero_grad()
        loss.backward()
        opt.step()
    p.eval()
    return p


def test_discover_modes_recovers_the_four_routes(embedded):
    found = embedded.discover_modes()
    true = {int(e): int(m) for e, m in zip(embedded.model.behavior_episode, embedded.model.behavior_mode, strict=True)}
    episodes = sorted(true)
    ari = adjusted_rand_score([true[e] for e in episodes], [found.labels[e] for e in episodes])
    assert found.k == 4 and ari >= 0.9, (found.k, ari, found.silhouette)
    assert set(found.means) == set(range(4)) and all(m.shape == (2,) for m in found.means.values())
    assert max(found.silhouette, key=found.silhouette.get) == 4
    assert embedded.discover_modes(k=3).k == 3


def test_mode_latents_fall_back_to_discovered_modes_with_a_warning(embedded, caplog):
    labeled = embedded.mode_latents()
    saved = embedded.model.behavior_mode.clone()
    try:
        embedded.model.behavior_mode = torch.full_like(saved, -1)  # an instruction-string dataset
        with caplog.at_level(logging.WARNING):
            means = embedded.mode_latents()
        assert "no mode labels" in caplog.text and "discover_modes" in caplog.text
        assert len(means) == 4
        # every discovered mean lies next to one labeled mode's mean (same clusters, other ids)
        nearest = {min(labeled, key=lambda m: float((labeled[m] - z).norm())) for z in means.values()}
        assert nearest == set(labeled)
        embedded.set_latent(means[0])  # and steers like any latent
    finally:
        embedded.model.behavior_mode = saved


def test_cluster_choice_errors_are_named():
    feats = np.random.default_rng(0).normal(size=(10, 2))
    with pytest.raises(ValueError, match=r"k must be between 1 and the number of training episodes \(10\), got 11"):
        cluster_episodes(feats, k=11)
    with pytest.raises(ValueError, match="choosing k needs at least 3 training episodes"):
        cluster_episodes(feats[:2])
    labels, k, _ = cluster_episodes(feats, k=1)
    assert k == 1 and set(labels.tolist()) == {0}


def test_latent_map_cli_draws_any_checkpoint_labels_or_clusters(embedded, tmp_path, capsys):
    from lerobot_pdp.cli import main

    ckpt = tmp_path / "ckpt"
    embedded.save_pretrained(ckpt)
    assert main(["latent-map", str(ckpt), "--out", str(tmp_path / "map.png")]) == 0
    assert (tmp_path / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["latent-map", str(ckpt), "--out", str(tmp_path / "clusters.png"), "--k", "4"]) == 0
    assert (tmp_path / "clusters.png").stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt", "clusters.png", "map.png"]  # no temp files
    capsys.readouterr()
    assert main(["latent-map", str(tmp_path), "--out", str(tmp_path / "x.png")]) == 2
    assert "holds no model.safetensors" in capsys.readouterr().err
