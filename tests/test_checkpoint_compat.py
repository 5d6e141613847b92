"""Checkpoints written by an older release (tests/data/pdp_checkpoints_v2, README there) load and act as they
did: a trained one through LeRobot's saved processors, an adapted one (one latent and a sampler noise per chunk),
a taught one (its new mode) and a pick-place one with gripper phases (a latent per phase)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors

from lerobot_pdp import PDPPolicy

DATA = Path(__file__).parent / "data" / "pdp_checkpoints_v2"
EXPECTED = json.loads((DATA / "expected.json").read_text())


def _actions(policy, pre, post, observations: dict, latent=None) -> np.ndarray:
    """``select_action`` on each observation in turn after ``reset()`` and seed 0 (as the record was made)."""
    if latent is not None:
        policy.set_latent(torch.as_tensor(latent, dtype=torch.float32))
    policy.reset()
    torch.manual_seed(0)
    n = len(next(iter(observations.values())))
    out = []
    with torch.no_grad():
        for i in range(n):
            frame = {k: torch.tensor(v[i], dtype=torch.float32)[None] for k, v in observations.items()}
            out.append(post(policy.select_action(pre({**frame, "task": [""]})))[0].numpy())
    return np.stack(out)


@pytest.mark.parametrize("kind", sorted(EXPECTED))
def test_an_older_releases_checkpoint_acts_as_it_did(kind):
    rec = EXPECTED[kind]
    policy = PDPPolicy.from_pretrained(DATA / kind)
    policy.eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(DATA / kind))
    means = policy.mode_latents()
    assert sorted(means) == sorted(int(m) for m in rec["mode_latents"])
    for m, z in rec["mode_latents"].items():
        np.testing.assert_allclose(means[int(m)].numpy(), z, atol=1e-5)
    obs = rec["observations"]
    for tag, want in rec["actions"].items():
        if tag == "as_loaded":
            latent = None  # its adaptation (adapted), or its default (trained, taught)
        elif tag == "fixed_z":
            latent = [0.3, -0.2]
        else:
            latent = rec["mode_latents"][tag.removeprefix("mode").removesuffix("_own")]
        got = _actions(policy, pre, post, obs, latent)
        np.testing.assert_allclose(got, np.asarray(want), atol=1e-4, err_msg=f"{kind}: {tag}")
