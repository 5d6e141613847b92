"""The latent's geometry and steering on reach-around (real MuJoCo), with PDP trained by a real `lerobot-train`."""

import numpy as np
import pytest
import torch

from lerobot_pdp.benchmark.rollouts import run_rollouts
from lerobot_pdp.benchmark.training import load_policy
from lerobot_pdp.envs import get_suite_env
from lerobot_pdp.envs.suite import parse_task_mode
from lerobot_pdp.episodes import read_episodes

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(reach_around_pdp):
    return load_policy(reach_around_pdp)


def test_checkpoint_has_processors_and_config(reach_around_pdp):
    names = {p.name for p in reach_around_pdp.iterdir()}
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"} <= names


def test_a_encoded_episodes_separate_by_mode(trained):
    policy, _, _ = trained
    table = policy.behavior_table()
    z, modes = table["z"], table["mode"]
    assert len(np.unique(modes)) == 8
    means = {m: z[modes == m].mean(0) for m in np.unique(modes)}
    pred = [min(means, key=lambda m: np.linalg.norm(zi - means[m])) for zi in z]
    acc = float(np.mean(np.array(pred) == modes))
    assert acc >= 0.95, acc


def test_b_trace_and_latent_distances_rank_correlate(trained):
    policy, _, _ = trained
    z = policy.behavior_table()["z"]
    dz = np.linalg.norm(z[:, None] - z[None], axis=-1)
    dx = policy.model.bank.distances.numpy()
    iu = np.triu_indices(len(z), 1)
    rank = lambda v: np.argsort(np.argsort(v))  # noqa: E731
    rho = np.corrcoef(rank(dz[iu]), rank(dx[iu]))[0, 1]  # Spearman's rank correlation
    assert rho > 0.7, rho


def test_c_mode_latent_generates_that_modes_route(trained):
    """Conditioned on a mode's mean latent, the rollout takes that mode's route (the env's classifier)."""
    policy, pre, post = trained
    suite = get_suite_env("reach-around")
    torch.manual_seed(0)
    hits, total = 0, 0
    for mode, z in policy.mode_latents().items():
        policy.set_latent(z)
        batch = run_rollouts(suite, 0, policy, pre, post, 2, seed=200 + mode)
        hits += sum(r.success and r.mode == mode for r in batch.results)
        total += len(batch.results)
    assert hits / total >= 0.9, f"{hits}/{total} rollouts succeeded along their conditioned mode"


def test_d_fit_latent_on_held_out_demo_lands_nearest_its_mode(trained, tmp_path):
    from lerobot_pdp.envs.recording import make_dataset

    policy, pre, post = trained
    suite = get_suite_env("reach-around")
    # one new demonstration per mode, never seen in training (another data seed)
    held = make_dataset("reach-around", tmp_path / "held", scene=0, episodes_per_mode=1, seed=123, progress=False)
    means = policy.mode_latents()
    episodes = read_episodes(held, ["observation.state"])
    assert len(episodes) == len(means) == 8
    for ep, data in episodes.items():
        mode = parse_task_mode(data["task"])
        res = policy.fit_latent((held, ep), steps=50)
        nearest = min(means, key=lambda m: float((means[m] - res.z).norm()))
        assert nearest == mode, (ep, mode, res.z, {m: v.tolist() for m, v in means.items()})
        # fit_latent activated the fitted z: the policy now drives that mode's route
        (r,) = run_rollouts(suite, 0, policy, pre, post, 1, seed=300 + ep).results
        assert r.success and r.mode == mode, (ep, mode, r)
