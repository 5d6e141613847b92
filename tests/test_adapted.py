"""Adapted checkpoints: the adaptation saved with a checkpoint, loaded in another process's way (from disk),
acting adapted from the first chunk; ``lerobot-pdp adapt`` writing a complete one; the base kept bit for bit."""

from __future__ import annotations

import filecmp
import json
import logging
import re
import shutil

import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors
from policies import small_policy

from lerobot_pdp import PDPPolicy
from lerobot_pdp.checkpoint import ADAPTATION_INFO, ADAPTATION_TENSORS
from lerobot_pdp.cli import main as cli


def _obs(p):
    """A normalised observation history [2, n_obs_steps, dim] as LeRobot's preprocessor hands it over."""
    g = torch.Generator().manual_seed(3)
    return {k: torch.rand(2, p.config.n_obs_steps, ft.shape[0], generator=g) * 2 - 1
            for k, ft in p.config.condition_features.items()}


def info_noises(out) -> int:
    return json.loads((out / ADAPTATION_INFO).read_text())["noise_chunks"]


def _chunks(p, obs, n=3):
    p.reset()
    torch.manual_seed(0)
    return torch.stack([p.predict_action_chunk(obs) for _ in range(n)])


def test_fit_then_save_pretrained_keeps_the_adaptation(synthetic_meta, tmp_path, caplog):
    p = small_policy(synthetic_meta)
    p.eval()
    res = p.fit_latent((synthetic_meta.root, 2), steps=2, noise="chunks")
    p.save_pretrained(tmp_path / "adapted")
    info = json.loads((tmp_path / "adapted" / ADAPTATION_INFO).read_text())
    assert info["source"] == "fit_latent" and info["latent"] == [res.z.tolist()]  # [M, d_z]
    assert info["demonstration"] == {"dataset": str(synthetic_meta.root.resolve()), "episode": 2}
    assert info["fit"]["steps"] == 2 and info["fit"]["noise"] == "chunks" and info["fit"]["lr"] == p.config.fit_lr
    assert info["fit"]["optimizer"] == "adam"
    assert info["noise_chunks"] == len(res.noise) > 1 and "error_ratio" in info and info["date"]
    assert (tmp_path / "adapted" / ADAPTATION_TENSORS).stat().st_size < 20_000  # small beside the weights

    q = PDPPolicy.from_pretrained(tmp_path / "adapted")
    q.eval()
    assert torch.equal(q.active_latent, p.active_latent) and torch.equal(q.active_noise, p.active_noise)
    assert q.steering.provenance["demonstration"]["episode"] == 2
    weights_p, weights_q = p.state_dict(), q.state_dict()
    assert weights_p.keys() == weights_q.keys()
    for k in weights_p:  # bit for bit (train_loss_dp is NaN in an untrained policy)
        torch.testing.assert_close(weights_q[k], weights_p[k], rtol=0, atol=0, equal_nan=True, msg=k)
    obs = _obs(p)
    torch.testing.assert_close(_chunks(q, obs), _chunks(p, obs))  # adapted from the first chunk, noises in order

    q.set_latent(None)  # back to the base behaviour
    assert len(q.active_latent) == 0 and len(q.active_noise) == 0
    cfg = PDPPolicy.from_pretrained(tmp_path / "adapted").config
    cfg.use_adaptation = False  # what --policy.use_adaptation=false does
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.checkpoint"):
        assert len(PDPPolicy.from_pretrained(tmp_path / "adapted", config=cfg).active_latent) == 0
    assert "loaded without its adaptation (use_adaptation=false): acting as its base" in caplog.text  # said
    # loaded to train (lerobot-train --policy.path=ADAPTED passes the dataset): trained and saved without it
    from lerobot.policies.factory import make_policy

    cfg = PDPPolicy.from_pretrained(tmp_path / "adapted").config
    cfg.pretrained_path = tmp_path / "adapted"
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.checkpoint"):
        trained = make_policy(cfg, ds_meta=synthetic_meta)
    assert len(trained.active_latent) == 0 and len(trained.active_noise) == 0
    assert "is an adapted checkpoint" in caplog.text and "trains and is saved without it" in caplog.text
    trained.save_pretrained(tmp_path / "fine_tuned")
    assert not (tmp_path / "fine_tuned" / ADAPTATION_TENSORS).exists()
    q.save_pretrained(tmp_path / "adapted")  # a policy without an adaptation leaves no stale adaptation files
    assert not (tmp_path / "adapted" / ADAPTATION_TENSORS).exists()
    assert not (tmp_path / "adapted" / ADAPTATION_INFO).exists()


def test_set_latent_and_steering_fields_travel_with_the_checkpoint(synthetic_meta, tmp_path):
    p = small_policy(synthetic_meta)
    p.set_latent([0.25, -0.5])
    p.save_pretrained(tmp_path / "a")
    assert json.loads((tmp_path / "a" / ADAPTATION_INFO).read_text())["source"] == "set_latent"
    q = PDPPolicy.from_pretrained(tmp_path / "a")
    assert q.active_latent.tolist() == [[0.25, -0.5]]
    cfg = q.config
    cfg.steer_latent = [1.0, 1.0]  # a steering field overrides the stored adaptation
    assert PDPPolicy.from_pretrained(tmp_path / "a", config=cfg).active_latent.tolist() == [[1.0, 1.0]]
    # saved from Python, a folder lerobot-eval loads: the processors built from the policy's statistics ("a"), or
    # those of the checkpoint it was loaded from, as they are (its rename map, its device step)
    pre = json.loads((tmp_path / "a" / "policy_preprocessor.json").read_text())
    pre["steps"][0]["config"]["rename_map"] = {"observation.robot_state": "observation.state"}
    (tmp_path / "a" / "policy_preprocessor.json").write_text(json.dumps(pre))
    q = PDPPolicy.from_pretrained(tmp_path / "a")
    q.set_latent([0.5, 0.5])
    q.save_pretrained(tmp_path / "b")
    for f in (tmp_path / "a").glob("policy_*processor*"):
        assert (tmp_path / "b" / f.name).read_bytes() == f.read_bytes(), f.name


def test_a_checkpoint_saved_after_load_time_steering_keeps_the_result_not_the_instruction(synthetic_meta, tmp_path,
                                                                                         caplog):
    """Loaded with --policy.steer_dataset_root (a start-up fit) and saved: the fitted latent is its adaptation and
    the steer_* fields are not saved, so the checkpoint, moved and without the recording, loads as it was saved
    instead of fitting again (or not finding the recording). An adapted checkpoint of a base whose config steers it
    acts under its adaptation; a policy built to train is not steered, and says so."""
    import dataclasses

    from lerobot.policies.factory import make_policy

    from lerobot_pdp.adapted import adapt_checkpoint
    from lerobot_pdp.configuration_pdp import STEERING_FIELDS

    p = small_policy(synthetic_meta)
    p.save_pretrained(tmp_path / "ckpt")
    shutil.copytree(synthetic_meta.root, tmp_path / "demo")
    cfg = dataclasses.replace(p.config, steer_dataset_root=str(tmp_path / "demo"), steer_episode_index=2, fit_steps=2,
                              use_adaptation=False)
    q = PDPPolicy.from_pretrained(tmp_path / "ckpt", config=cfg)
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.checkpoint"):
        q.save_pretrained(tmp_path / "saved")
    assert f"without steer_dataset_root='{tmp_path / 'demo'}', steer_episode_index=2" in caplog.text
    saved = json.loads((tmp_path / "saved" / "config.json").read_text())
    assert all(saved[f] is None for f in STEERING_FIELDS) and saved["use_adaptation"] is True
    shutil.rmtree(tmp_path / "demo")
    shutil.move(tmp_path / "saved", tmp_path / "moved")
    assert torch.equal(PDPPolicy.from_pretrained(tmp_path / "moved").active_latent, q.active_latent)

    mode = sorted(p.mode_latents())[1]
    p.config.steer_mode = mode  # a base whose config.json steers every load of it (lerobot-train --policy.steer_mode)
    p.save_pretrained(tmp_path / "steered")
    assert json.loads((tmp_path / "steered" / "config.json").read_text())["steer_mode"] == mode  # kept: not acted on
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.adapted"):
        adapt_checkpoint(tmp_path / "steered", (synthetic_meta.root, 2), tmp_path / "adapted", steps=2)
    assert f"steers it as it loads (steer_mode={mode})" in caplog.text
    fitted = json.loads((tmp_path / "adapted" / ADAPTATION_INFO).read_text())["latent"]
    assert PDPPolicy.from_pretrained(tmp_path / "adapted").active_latent.tolist() == fitted  # not mode's latent

    cfg = PDPPolicy.from_pretrained(tmp_path / "steered").config
    cfg.pretrained_path = tmp_path / "steered"  # lerobot-train --policy.path=steered (fine-tuning)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.steering"):
        trained = make_policy(cfg, ds_meta=synthetic_meta)
    assert len(trained.active_latent) == 0
    assert f"steering given to a training run (steer_mode={mode}): PDP does not steer the policy it trains" in caplog.text


def test_an_adaptation_of_phase_latents_saved_on_a_policy_without_phases_still_loads(synthetic_meta, tmp_path,
                                                                                     caplog):
    """Saved before several latents were refused on a policy without phases: it loads, acting under the first
    latent as it did, and says so."""
    from safetensors.torch import save_file

    p = small_policy(synthetic_meta)
    p.set_latent([0.25, -0.5])
    p.save_pretrained(tmp_path / "a")
    save_file({"latent": torch.tensor([[0.25, -0.5], [1.0, 1.0]]), "noise": torch.zeros(0)},
              str(tmp_path / "a" / ADAPTATION_TENSORS))
    with caplog.at_level("WARNING"):
        q = PDPPolicy.from_pretrained(tmp_path / "a")
    assert q.active_latent.tolist() == [[0.25, -0.5]] and "acting under the first" in caplog.text


def test_a_damaged_adaptation_file_is_named(synthetic_meta, tmp_path):
    p = small_policy(synthetic_meta)
    p.set_latent([0.25, -0.5])
    p.save_pretrained(tmp_path / "a")
    f = tmp_path / "a" / ADAPTATION_TENSORS
    f.write_bytes(f.read_bytes()[:20])
    with pytest.raises(ValueError, match=r"adaptation files .* are damaged .*use_adaptation=false"):
        PDPPolicy.from_pretrained(tmp_path / "a")


def _base_checkpoint(meta, path):
    """A checkpoint as lerobot-train writes one: weights, config, processors."""
    p = small_policy(meta)
    p.save_pretrained(path)
    pre, post = make_pre_post_processors(p.config, dataset_stats=meta.stats)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    (path / "README.md").write_text("# a model card\n")
    return p


def test_lerobot_pdp_adapt_writes_a_complete_adapted_checkpoint(synthetic_meta, tmp_path, capsys, monkeypatch):
    import tqdm.auto

    bars = []  # both fits show a progress bar (the test suite hides tqdm's output: TQDM_DISABLE)

    class Bar(tqdm.auto.tqdm):
        def __init__(self, *a, **k):
            bars.append(k.get("desc"))
            super().__init__(*a, **k)

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    base, out = tmp_path / "base", tmp_path / "adapted"
    _base_checkpoint(synthetic_meta, base)
    assert cli(["adapt", str(base), "--demo", str(synthetic_meta.root), "--episode", "2", "--steps", "2",
                "--noise", "chunks", "--out", str(out)]) == 0
    cli_out = capsys.readouterr().out
    assert re.search(r"adaptation files adaptation\.json \(\d+\.\d kB\), adaptation\.safetensors \(\d+\.\d kB\)", cli_out)
    assert bars[-2:] == ["fit_latent", f"fit {info_noises(out)} chunk noises"], bars
    for f in base.iterdir():  # every file of the base, the weights bit for bit
        assert filecmp.cmp(f, out / f.name, shallow=False) or f.name == "README.md", f.name
    assert "## Adaptation" in (out / "README.md").read_text()
    info = json.loads((out / ADAPTATION_INFO).read_text())
    assert info["demonstration"]["episode"] == 2 and info["noise_chunks"] > 1
    assert info["base_checkpoint"] == str(base.resolve())
    q = PDPPolicy.from_pretrained(out)
    assert q.active_latent.tolist() == info["latent"] and len(q.active_noise) == info["noise_chunks"]
    assert not list(tmp_path.glob(".pdp-adapt-*"))  # nothing half-written left beside it
    assert "(of the latent alone)" in cli_out and "error ratio" in cli_out  # the ratio is z's, before the noises
    # saved over from Python: the card's section follows the adaptation it now holds (or goes with it)
    resaved = tmp_path / "resaved"
    shutil.copytree(out, resaved)
    q.set_latent(q.mode_latents()[1])
    q.save_pretrained(resaved)
    card = (resaved / "README.md").read_text()
    assert card.count("## Adaptation") == 1 and str(q.active_latent.tolist()) in card and "noises" not in card
    q.set_latent(None)
    q.save_pretrained(resaved)
    assert "## Adaptation" not in (resaved / "README.md").read_text() and not (resaved / ADAPTATION_INFO).exists()
    # an existing output is refused by name; so is a folder that is no checkpoint
    assert cli(["adapt", str(base), "--demo", str(synthetic_meta.root), "--out", str(out)]) == 2
    assert f"{out} exists" in capsys.readouterr().err
    # an output inside the base would be copied into itself (with its staging folder): refused before any work
    assert cli(["adapt", str(base), "--demo", str(synthetic_meta.root), "--out", str(base / "adapted")]) == 2
    assert f"{base / 'adapted'} lies inside the checkpoint {base}" in capsys.readouterr().err
    assert sorted(f.name for f in base.iterdir() if f.is_dir()) == []
    assert cli(["adapt", str(tmp_path), "--demo", str(synthetic_meta.root), "--out", str(tmp_path / "x")]) == 2
    assert "is not a PDP checkpoint folder" in capsys.readouterr().err
    last = tmp_path / "train" / "checkpoints" / "last"  # LeRobot's layout: the checkpoint is its pretrained_model
    shutil.copytree(base, last / "pretrained_model")
    assert cli(["adapt", str(last), "--demo", str(synthetic_meta.root), "--out", str(tmp_path / "x")]) == 2
    assert f"; did you mean {last / 'pretrained_model'}?" in capsys.readouterr().err
    with monkeypatch.context() as m:  # a missing recording is named before the checkpoint is loaded
        m.setattr("lerobot_pdp.adapted.load_base_policy", None)
        assert cli(["adapt", str(base), "--demo", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 2
    assert f"recording {tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err
    # an adapted checkpoint adapted again: its weights are fitted, the new adaptation replaces the old (one card
    # section, one adaptation), whether or not the base it names is at hand
    assert cli(["adapt", str(out), "--demo", str(synthetic_meta.root), "--episode", "1", "--steps", "1",
                "--out", str(tmp_path / "twice")]) == 0
    twice = json.loads((tmp_path / "twice" / ADAPTATION_INFO).read_text())
    assert twice["demonstration"]["episode"] == 1 and twice["noise_chunks"] == 0
    assert twice["base_checkpoint"] == str(base.resolve())  # the base of the adapted checkpoint adapted again
    assert (tmp_path / "twice" / "README.md").read_text().count("## Adaptation") == 1
    assert filecmp.cmp(out / "model.safetensors", tmp_path / "twice" / "model.safetensors", shallow=False)
    # a base without a model card (lerobot-train writes one only when it pushes) gets PDP's card with the section
    (base / "README.md").unlink()
    assert cli(["adapt", str(base), "--demo", str(synthetic_meta.root), "--steps", "1", "--out", str(tmp_path / "c")]) == 0
    card = (tmp_path / "c" / "README.md").read_text()
    assert "Parameterized Diffusion Policy" in card and card.count("## Adaptation") == 1
