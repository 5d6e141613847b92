"""``compile_model``: the torch.compile'd denoiser computes what the eager one does (sampler and training
loss), survives a copy, and a bad ``compile_mode`` is refused. Compiling on a CPU takes a minute: slow."""

from __future__ import annotations

import copy

import pytest
import torch
from policies import small_policy, training_batch

from lerobot_pdp import PDPConfig


def test_unknown_compile_mode_is_refused():
    with pytest.raises(ValueError, match="compile_mode must be one of .*'fastest'"):
        PDPConfig(compile_mode="fastest")


@pytest.mark.slow
def test_compiled_denoiser_samples_and_trains_like_the_eager_one(synthetic_meta):
    eager = small_policy(synthetic_meta)
    compiled = small_policy(synthetic_meta, compile_model=True)
    compiled.load_state_dict(eager.state_dict())
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(2, eager.model.denoiser.obs_cond_dim, generator=g)
    z = torch.randn(2, eager.config.latent_dim, generator=g)
    noise = torch.randn(2, eager.config.horizon, eager.action_dim, generator=g)
    for p in (eager, compiled):
        p.eval()
    want = eager.generate(obs, z, noise=noise)
    torch.testing.assert_close(compiled.generate(obs, z, noise=noise), want, atol=1e-4, rtol=1e-4)
    assert set(compiled.model._compiled_fns) == {"sample"}
    with torch.no_grad():  # weights change in place (an optimizer step): the compiled code reads them
        for a, b in zip(eager.parameters(), compiled.parameters(), strict=True):
            d = 0.01 * torch.randn_like(a)
            a.add_(d)
            b.add_(d)
    torch.testing.assert_close(compiled.generate(obs, z, noise=noise), eager.generate(obs, z, noise=noise),
                               atol=1e-4, rtol=1e-4)

    batch = training_batch(synthetic_meta, eager)
    for p in (eager, compiled):
        p.train()
    torch.manual_seed(1)
    loss_e, _ = eager.model.loss_terms(batch)
    torch.manual_seed(1)
    loss_c, _ = compiled.model.loss_terms(batch)
    torch.testing.assert_close(loss_c, loss_e, atol=1e-4, rtol=1e-4)
    loss_e.backward()
    loss_c.backward()
    for (name, a), b in zip(eager.named_parameters(), compiled.parameters(), strict=True):
        if a.grad is not None:
            torch.testing.assert_close(b.grad, a.grad, atol=1e-4, rtol=1e-3, msg=name)
    assert set(compiled.model._compiled_fns) == {"sample", "train"}
    twin = copy.deepcopy(compiled)  # compiled code is not copied: the copy compiles its own on use
    assert twin.model._compiled_fns == {} and twin.config.compile_model
    torch.testing.assert_close(twin.generate(obs, z, noise=noise), eager.generate(obs, z, noise=noise),
                               atol=1e-4, rtol=1e-4)


@pytest.mark.slow
def test_lerobot_rollouts_torch_compile_wrapper_acts_like_the_eager_policy(synthetic_meta):
    """``lerobot-rollout --use_torch_compile=true`` sets ``compile_model`` and wraps ``predict_action_chunk``
    in torch.compile (LeRobot's own wrapper, used here): the chunks stay those of the eager policy."""
    from lerobot.rollout.context import _wrap_predict_action_chunk_with_torch_compile

    eager = small_policy(synthetic_meta)
    p = small_policy(synthetic_meta, compile_model=True)
    p.load_state_dict(eager.state_dict())
    assert _wrap_predict_action_chunk_with_torch_compile(p, backend="inductor", mode="default")
    obs = {"observation.state": torch.zeros(1, 2), "observation.environment_state": torch.zeros(1, 2)}
    for q in (eager, p):
        q.eval()
        q.set_latent(q.behavior_latents()[0].detach())
        q.reset()
        q.select_action(dict(obs))  # fills the observation history
    for seed in range(3):
        noise = torch.randn(1, p.config.horizon, p.action_dim, generator=torch.Generator().manual_seed(seed))
        torch.testing.assert_close(p.predict_action_chunk(dict(obs), noise=noise),
                                   eager.predict_action_chunk(dict(obs), noise=noise), atol=1e-4, rtol=1e-4)
