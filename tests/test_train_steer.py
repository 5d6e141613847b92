"""The steering claim on a synthetic multimodal dataset, with PDP trained by a real `lerobot-train` process."""

import numpy as np
import pytest
import torch

from lerobot_pdp import PDPPolicy
from lerobot_pdp.behavior import read_episodes
from lerobot_pdp.soft_dtw import dtw

from synthetic import classify, rollout

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(trained_checkpoint):
    from lerobot.policies.factory import make_pre_post_processors

    policy = PDPPolicy.from_pretrained(trained_checkpoint)
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(trained_checkpoint))
    return policy, pre, post


def test_checkpoint_has_processors_and_config(trained_checkpoint):
    names = {p.name for p in trained_checkpoint.iterdir()}
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"} <= names


def test_a_encoded_episodes_separate_by_mode(trained):
    policy, _, _ = trained
    table = policy.behavior_table()
    z, modes = table["z"], table["mode"]
    means = {m: z[modes == m].mean(0) for m in np.unique(modes)}
    pred = [min(means, key=lambda m: np.linalg.norm(zi - means[m])) for zi in z]
    acc = float(np.mean(np.array(pred) == modes))
    assert acc >= 0.95, acc


def test_b_trace_and_latent_distances_rank_correlate(trained):
    policy, _, _ = trained
    z = policy.behavior_table()["z"]
    dz = np.linalg.norm(z[:, None] - z[None], axis=-1)
    dx = policy.trace_distance_matrix.numpy()
    iu = np.triu_indices(len(z), 1)
    rank = lambda v: np.argsort(np.argsort(v))  # noqa: E731
    rho = np.corrcoef(rank(dz[iu]), rank(dx[iu]))[0, 1]  # Spearman's rank correlation
    assert rho > 0.7, rho


def test_c_mode_latent_generates_that_modes_path(trained, synthetic_dataset):
    policy, pre, post = trained
    eps = read_episodes(synthetic_dataset, ["observation.state"])
    demos = {ep: (d["observation.state"], int(d["task"].split()[1].rstrip(":"))) for ep, d in eps.items()}
    hits, total = 0, 0
    torch.manual_seed(0)
    for mode, z in policy.mode_latents().items():
        policy.set_latent(z)
        for _ in range(3):
            path = rollout(policy, pre, post)
            # closest demonstration by DTW decides which mode the generated path is
            nearest = min(demos.values(), key=lambda d: dtw(path, d[0]))
            hits += nearest[1] == mode
            total += 1
            assert classify(path) == mode or nearest[1] != mode
    assert hits / total >= 0.9, f"{hits}/{total} rollouts followed their conditioned mode"


def test_d_fit_latent_on_held_out_demo_lands_nearest_its_mode(trained, tmp_path):
    from synthetic import write_dataset

    policy, pre, post = trained
    held = write_dataset(tmp_path / "held", episodes_per_mode=1, seed=123)  # demos never seen in training
    means = policy.mode_latents()
    for ep in range(4):
        res = policy.fit_latent((held, ep), steps=50)
        nearest = min(means, key=lambda m: float((means[m] - res.z).norm()))
        assert nearest == ep, (ep, res.z, {m: v.tolist() for m, v in means.items()})
        assert classify(rollout(policy, pre, post)) == ep
