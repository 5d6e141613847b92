"""Teaching a new mode: the demonstration joins the behaviour bank as a new mode with the encoder's latent, only the
denoiser moves, the old modes keep their latents, the taught checkpoint carries it all; bad inputs are named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from policies import small_policy

from lerobot_pdp import PDPPolicy
from lerobot_pdp.cli import main as cli
from lerobot_pdp.latent_fitting import demonstration_error
from lerobot_pdp.taught import TEACHING_INFO
from lerobot_pdp.taught_demos import TAUGHT_DEMOS

from synthetic import GOAL, MAX_STEP, MODES, START, write_dataset


def new_route(x_via: float = 1.6, hold: int = 4) -> dict[str, np.ndarray]:
    """A demonstration of a route none of the synthetic modes takes: around the disc far out on the right, via
    a second way-point above the goal."""
    pts = [START, np.array([x_via, -0.2]), np.array([x_via * 0.5, 1.4]), GOAL]
    pos = [START.copy()]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = int(np.ceil(np.linalg.norm(b - a) / (0.7 * MAX_STEP)))
        pos += [a + (b - a) * i / n for i in range(1, n + 1)]
    pos = np.concatenate([np.array(pos), np.repeat(np.array(pos[-1:]), hold, axis=0)])
    act = np.clip(np.diff(pos, axis=0, append=pos[-1:]) / MAX_STEP, -1, 1)
    return {"observation.state": pos.astype(np.float32), "action": act.astype(np.float32),
            "observation.environment_state": np.repeat(GOAL[None].astype(np.float32), len(pos), axis=0)}


def _params(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_teach_adds_a_mode_moving_only_the_denoiser(synthetic_meta):
    p = small_policy(synthetic_meta)
    old_modes = {m: z.clone() for m, z in p.mode_latents().items()}
    vae, obs_enc, den = _params(p.model.vae), _params(p.model.obs_encoder), _params(p.model.denoiser)
    n = len(p.model.bank.traces)
    demo = new_route()
    res = p.teach(demo, synthetic_meta.root, steps=3, seed=0, name="far right")

    assert res.mode == 4 and res.steps == 3 and len(res.losses) == 3
    assert all(w.grad is None for w in p.model.denoiser.parameters())  # no gradient left on the weights
    assert res.rehearsal_windows == sum(int(e - s) for s, e in zip(p.model.bank.start[:n], p.model.bank.end[:n],
                                                                  strict=True))
    assert res.demo_windows == len(demo["action"]) and np.isfinite(res.nearest_spreads)
    modes = p.mode_latents()
    assert sorted(modes) == [0, 1, 2, 3, 4] and modes.names[4] == "far right"
    for m, z in old_modes.items():  # the encoder did not move: every old mode keeps its latent (up to the float
        torch.testing.assert_close(modes[m], z, rtol=0, atol=1e-6)  # rounding of a batch one behaviour larger)
    torch.testing.assert_close(modes[4], res.z[0], rtol=0, atol=1e-6)  # the new mode: the encoder's latent of the demo
    assert len(p.model.bank.traces) == n + 1 and p.model.bank.distances.shape == (n + 1, n + 1)
    from lerobot_pdp.latent_map import latent_map_figure

    fig = latent_map_figure(p).figure  # the taught mode is drawn as one, and said to be taught
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert "4: far right, taught" in labels and "taught modes" in fig.get_suptitle()
    __import__("matplotlib.pyplot").pyplot.close(fig)
    import lerobot_pdp.latent_map as latent_map

    panels, latent_map.MAX_PANELS = latent_map.MAX_PANELS, 3  # more modes than panels: the taught one's comes first
    try:
        fig = latent_map_figure(p).figure
    finally:
        latent_map.MAX_PANELS = panels
    assert [a.get_title() for a in fig.axes[1:]] == ["0: " + MODES[0][0], "1: " + MODES[1][0], "4: far right, taught"]
    assert "traces of 3 of 5 shown, taught modes first" in fig.get_suptitle()
    __import__("matplotlib.pyplot").pyplot.close(fig)
    d = p.model.bank.distances
    torch.testing.assert_close(d, d.T)
    assert float(d[-1, :-1].min()) > 0  # a route of its own, away from every training behaviour
    for before, module in ((vae, p.model.vae), (obs_enc, p.model.obs_encoder)):
        for k, v in module.state_dict().items():
            torch.testing.assert_close(v, before[k], rtol=0, atol=0, msg=k)
    assert any(not torch.equal(v, den[k]) for k, v in p.model.denoiser.state_dict().items())


def test_teaching_makes_the_new_route_the_denoisers_own(synthetic_meta):
    """After teaching, the denoiser reproduces the demonstration at its new latent clearly better than before, while
    the training demonstrations' error at their own latents stays where it was. The denoiser first learns the
    training data (teaching an untrained one lowers every error alike: it would tell teaching from nothing)."""
    p = small_policy(synthetic_meta, optimizer_lr=1e-3)
    demo = new_route()
    old_demo = (synthetic_meta.root, 1)
    # 200 rehearsal steps of the training windows (a quarter of each batch on a training episode, mode 4 a copy)
    p.teach(old_demo, synthetic_meta.root, steps=200, lr=3e-3, seed=0)
    z_new = p.encode(demo)[None]
    z_old = p.encode(old_demo)[None]

    def errors():
        return (demonstration_error(p.model.denoiser, p.model.noise_schedule, p.demo_windows(demo), z_new, 8, seed=0),
                demonstration_error(p.model.denoiser, p.model.noise_schedule, p.demo_windows(old_demo), z_old, 8, seed=0))

    new_before, old_before = errors()
    p.teach(demo, synthetic_meta.root, steps=60, lr=1e-3, seed=0)
    new_after, old_after = errors()
    # measured on three weight seeds: new 0.65-0.73 of before, old 0.93-1.07
    assert new_after < 0.85 * new_before, (new_before, new_after)
    assert 0.8 * old_before < old_after < 1.2 * old_before, (old_before, old_after)


def test_teaching_again_rehearses_the_mode_taught_before(synthetic_meta, caplog):
    """A second taught mode does not make the policy forget the first: the first demonstration is rehearsed at its
    latent (kept with the policy), as many windows per batch as the new one, and without it the first mode drifts.
    Measured on weight seeds 0 and 1: the first mode's error 0.97x / 0.99x with its rehearsal, 1.28x / 1.26x
    without."""
    import copy

    p = small_policy(synthetic_meta, optimizer_lr=1e-3)
    p.teach((synthetic_meta.root, 1), synthetic_meta.root, steps=200, lr=3e-3, seed=0, name="warm-up")
    first, second = new_route(1.6), new_route(-1.7)
    res = p.teach(first, synthetic_meta.root, steps=60, lr=1e-3, seed=0, name="far right")
    z_first = res.z

    def error(q):
        return demonstration_error(q.model.denoiser, q.model.noise_schedule, q.demo_windows(first), z_first, 8, seed=0)

    before = error(p)
    forgetful = copy.deepcopy(p)
    forgetful.model.bank.taught_demos.clear()  # as a checkpoint taught by a release that did not keep them
    p.teach(second, synthetic_meta.root, steps=60, lr=1e-3, seed=0, name="far left")
    with caplog.at_level("WARNING", logger="lerobot_pdp.teaching"):
        forgetful.teach(second, synthetic_meta.root, steps=60, lr=1e-3, seed=0, name="far left")
    assert "taught mode(s) [4, 5] were taught by a release that did not keep their demonstrations" in caplog.text
    kept, lost = error(p), error(forgetful)
    assert kept < 1.1 * before and kept < lost, (before, kept, lost)


def test_taught_checkpoint_loads_with_its_new_mode(synthetic_meta, tmp_path, capsys):
    base = tmp_path / "base"
    p = small_policy(synthetic_meta)
    p.config.steer_dataset_root = str(tmp_path / "gone")  # a base whose config.json fits at every load (not taught on)
    p.save_pretrained(base)
    demo_root = tmp_path / "demo"
    _write_demo(demo_root, new_route())
    code = cli(["teach", str(base), "--demo", str(demo_root), "--data", str(synthetic_meta.root), "--steps", "2",
                "--name", "far right", "--out", str(tmp_path / "taught")])
    assert code == 0 and "mode 4" in capsys.readouterr().out
    info = json.loads((tmp_path / "taught" / TEACHING_INFO).read_text())
    assert info["mode"] == 4 and info["settings"]["steps"] == 2 and info["demonstration"]["episode"] == 0
    assert info["training_data"] == str(synthetic_meta.root.resolve())
    assert json.loads((tmp_path / "taught" / "config.json").read_text())["steer_dataset_root"] is None
    card = (tmp_path / "taught" / "README.md").read_text()  # the base had no card (as lerobot-train leaves it)
    assert "Parameterized Diffusion Policy" in card and "## Taught mode" in card and "far right" in card

    q = PDPPolicy.from_pretrained(tmp_path / "taught")
    assert sorted(q.mode_latents()) == [0, 1, 2, 3, 4] and q.config.mode_names["4"] == "far right"
    torch.testing.assert_close(q.mode_latents()[4], torch.tensor(info["latent"][0]))
    cfg = q.config
    cfg.steer_mode = 4  # what --policy.steer_mode=4 does in lerobot-eval / lerobot-rollout
    r = PDPPolicy.from_pretrained(tmp_path / "taught", config=cfg)
    torch.testing.assert_close(r.active_latent, q.mode_latents()[4][None])

    # teaching the taught checkpoint again: its own taught episode is not mistaken for a foreign dataset, the
    # first taught demonstration is rehearsed too (kept with the checkpoint), and both are kept for the next time
    assert (tmp_path / "taught" / TAUGHT_DEMOS).is_file() and sorted(q.model.bank.taught_demos) == [4]
    damaged = tmp_path / "damaged"
    __import__("shutil").copytree(tmp_path / "taught", damaged)
    (damaged / TAUGHT_DEMOS).write_bytes(b"not a safetensors file")
    assert PDPPolicy.from_pretrained(damaged).model.bank.taught_demos == {}  # acts as saved; said in a warning
    second = tmp_path / "second"
    _write_demo(second, new_route(x_via=1.9))
    code = cli(["teach", str(tmp_path / "taught"), "--demo", str(second), "--data", str(synthetic_meta.root),
                "--steps", "1", "--name", "farther right", "--out", str(tmp_path / "taught2")])
    assert code == 0
    info2 = json.loads((tmp_path / "taught2" / TEACHING_INFO).read_text())
    assert info2["rehearsal_windows"] == info["rehearsal_windows"] + info["demo_windows"]
    assert [t["mode"] for t in info2["earlier_teachings"]] == [4] and info2["mode"] == 5  # both teachings recorded
    assert info2["loss_window"] == 1  # one step: its only loss, not a window counted as before and after
    assert info2["loss_first"] == info2["loss_last"] > 0 and "loss_first_50" not in info2
    r = PDPPolicy.from_pretrained(tmp_path / "taught2")
    assert sorted(r.mode_latents()) == [0, 1, 2, 3, 4, 5] and sorted(r.model.bank.taught_demos) == [4, 5]
    np.testing.assert_allclose(r.model.bank.taught_demos[4].arrays["action"], new_route()["action"], atol=1e-6)


def test_a_rehearsal_read_once_teaches_as_the_dataset_folder_does(synthetic_meta):
    """``read_rehearsal`` reads and checks the training dataset once for several teachings of one policy: a teaching
    from it is the teaching from the folder (same losses, same weights), and it refuses another policy."""
    import copy

    from lerobot_pdp.teaching import read_rehearsal

    p = small_policy(synthetic_meta)
    q = copy.deepcopy(p)
    a = p.teach(new_route(), synthetic_meta.root, steps=5, seed=0, name="far right")
    rehearsal = read_rehearsal(q, synthetic_meta.root)
    b = q.teach(new_route(), rehearsal, steps=5, seed=0, name="far right")
    assert a.losses == b.losses and a.rehearsal_windows == b.rehearsal_windows == len(rehearsal.windows.actions)
    torch.testing.assert_close(a.z, b.z)
    for (k, v), w in zip(p.model.denoiser.state_dict().items(), q.model.denoiser.state_dict().values(), strict=True):
        assert torch.equal(v, w), k
    c = q.teach(new_route(-1.7), rehearsal, steps=2, seed=0, name="far left")  # a second teaching, no new read
    assert c.mode == b.mode + 1 and c.rehearsal_windows == b.rehearsal_windows + len(new_route()["action"])
    with pytest.raises(ValueError, match="read for another policy"):
        p.teach(new_route(-1.7), rehearsal, steps=2, name="far left")


def test_taught_modes_dropped_by_training_are_taught_again_from_the_taught_checkpoint(synthetic_meta, tmp_path,
                                                                                       caplog, capsys, monkeypatch):
    """lerobot-train on a taught checkpoint with ``taught_rehearsal_share=0`` trains the dataset's behaviours alone:
    the taught modes are dropped with a warning that names them and the way back, ``teach <trained> --taught-from
    <taught>``, which teaches them again from the demonstrations the taught checkpoint keeps, in order and under
    their names."""
    import logging

    from lerobot.policies.factory import make_policy

    from lerobot_pdp import PDPConfig

    base = tmp_path / "base"
    small_policy(synthetic_meta).save_pretrained(base)
    demos = (tmp_path / "demo1", tmp_path / "demo2")
    _write_demo(demos[0], new_route())
    _write_demo(demos[1], new_route(x_via=1.9))
    data = ["--data", str(synthetic_meta.root), "--steps", "1"]
    assert cli(["teach", str(base), "--demo", str(demos[0]), *data, "--name", "far right", "--out",
                str(tmp_path / "t1")]) == 0
    assert cli(["teach", str(tmp_path / "t1"), "--demo", str(demos[1]), *data, "--name", "farther right", "--out",
                str(tmp_path / "t2")]) == 0

    cfg = PDPConfig.from_pretrained(tmp_path / "t2")  # what lerobot-train --policy.path builds, on the same dataset
    cfg.pretrained_path, cfg.taught_rehearsal_share = tmp_path / "t2", 0.0
    caplog.set_level(logging.WARNING, logger="lerobot_pdp.checkpoint")
    trained = make_policy(cfg, ds_meta=synthetic_meta)
    assert ("was taught mode(s) 4 ('far right'), 5 ('farther right'); with taught_rehearsal_share=0 lerobot-train "
            "does not rehearse them: they are dropped" in caplog.text)
    assert f"lerobot-pdp teach <trained checkpoint> --taught-from {tmp_path / 't2'} --out <folder>" in caplog.text
    assert sorted(trained.mode_latents()) == [0, 1, 2, 3] and not trained.model.bank.taught_demos
    trained.save_pretrained(tmp_path / "trained")
    assert not (tmp_path / "trained" / TAUGHT_DEMOS).exists()

    from lerobot_pdp import teaching

    reads = []
    check = teaching.check_training_data
    monkeypatch.setattr(teaching, "check_training_data", lambda *a: reads.append(a) or check(*a))
    capsys.readouterr()
    assert cli(["teach", str(tmp_path / "trained"), "--taught-from", str(tmp_path / "t2"), *data, "--out",
                str(tmp_path / "again")]) == 0
    assert len(reads) == 1  # two modes taught again, the training dataset read once
    out = capsys.readouterr().out
    assert f"mode 4 of {tmp_path / 't2'} -> mode 4" in out and f"mode 5 of {tmp_path / 't2'} -> mode 5" in out
    again = PDPPolicy.from_pretrained(tmp_path / "again")
    assert sorted(again.mode_latents()) == [0, 1, 2, 3, 4, 5]
    assert again.config.mode_names["4"] == "far right" and again.config.mode_names["5"] == "farther right"
    assert sorted(again.model.bank.taught_demos) == [4, 5]
    np.testing.assert_allclose(again.model.bank.taught_demos[5].arrays["action"], new_route(x_via=1.9)["action"],
                               atol=1e-6)
    info = json.loads((tmp_path / "again" / TEACHING_INFO).read_text())  # the second teaching rehearsed the first
    assert info["demonstration"] == {"taught_checkpoint": str((tmp_path / "t2").resolve()), "mode": 5}
    assert [t["demonstration"]["mode"] for t in info["earlier_teachings"]] == [4]
    assert info["base_checkpoint"] == info["earlier_teachings"][0]["base_checkpoint"] == str((tmp_path / "trained").resolve())
    assert info["rehearsal_windows"] == info["earlier_teachings"][0]["rehearsal_windows"] + len(new_route()["action"])
    assert "mode 5 kept by `t2`" in (tmp_path / "again" / "README.md").read_text()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".pdp-")) == []  # no stage left

    # argument errors, before anything is read
    for args, msg in (([], "give the demonstration with --demo, or a taught checkpoint"),
                      (["--demo", str(demos[0]), "--taught-from", str(tmp_path / "t2")], "(one of them)"),
                      (["--taught-from", str(tmp_path / "t2"), "--name", "x"], "--taught-from keeps the taught modes")):
        assert cli(["teach", str(tmp_path / "trained"), *args, "--out", str(tmp_path / "x")]) == 2
        assert msg in capsys.readouterr().err
    assert cli(["teach", str(tmp_path / "trained"), "--taught-from", str(base), *data, "--out", str(tmp_path / "x")]) == 2
    assert f"{base} keeps no taught demonstrations ({TAUGHT_DEMOS})" in capsys.readouterr().err
    # a base that kept the taught modes (lerobot-train's default) has nothing to be taught again; one that kept some
    # is taught the others
    assert cli(["teach", str(tmp_path / "t2"), "--taught-from", str(tmp_path / "t1"), *data, "--out",
                str(tmp_path / "x")]) == 2
    assert (f"{tmp_path / 't2'} still holds every mode taught to {tmp_path / 't1'}: 4 ('far right') (lerobot-train "
            "kept them): nothing to teach again") in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert cli(["teach", str(tmp_path / "t1"), "--taught-from", str(tmp_path / "t2"), *data, "--out",
                str(tmp_path / "t12")]) == 0
    assert f"mode 5 of {tmp_path / 't2'} -> mode 5" in capsys.readouterr().out
    assert sorted(PDPPolicy.from_pretrained(tmp_path / "t12").model.bank.taught_demos) == [4, 5]


def test_training_a_taught_checkpoint_further_rehearses_its_taught_modes(synthetic_meta, tmp_path, caplog):
    """Loaded to train on over its training dataset (what ``lerobot-train --policy.path`` / ``--resume`` builds), a
    taught checkpoint keeps its taught modes, named as taught: each training batch gets windows of the taught
    demonstrations, a quarter of the batch they make, at the taught latents; the windows are the teaching windows
    (hence the training loader's); L_embed trains on the dataset's behaviours alone; the checkpoint it saves keeps
    the modes and their demonstrations, and trains on again so."""
    import logging

    from lerobot.policies.factory import make_policy
    from policies import training_batch

    from lerobot_pdp import PDPConfig

    base = tmp_path / "base"
    small_policy(synthetic_meta, dataset_episodes=list(range(20))).save_pretrained(base)  # half the episodes
    _write_demo(tmp_path / "demo", new_route())
    assert cli(["teach", str(base), "--demo", str(tmp_path / "demo"), "--data", str(synthetic_meta.root), "--steps",
                "1", "--name", "far right", "--out", str(tmp_path / "taught")]) == 0
    taught = PDPPolicy.from_pretrained(tmp_path / "taught")
    assert taught.model.rehearsal is None  # loaded to act: nothing to rehearse

    def load_to_train(folder):
        cfg = PDPConfig.from_pretrained(folder)
        cfg.pretrained_path = folder
        return make_policy(cfg, ds_meta=synthetic_meta)

    caplog.set_level(logging.INFO, logger="lerobot_pdp")
    trained = load_to_train(tmp_path / "taught")
    n_demo = len(new_route()["action"])
    assert f"training rehearses taught mode(s) [4]: {n_demo} windows of their demonstrations, 25 % of each batch" \
        in caplog.text
    assert "dropped" not in caplog.text
    bank, rehearsal = trained.model.bank, trained.model.rehearsal
    assert sorted(trained.mode_latents()) == [0, 1, 2, 3, 4] and trained.config.mode_names["4"] == "far right"
    torch.testing.assert_close(trained.mode_latents()[4], taught.mode_latents()[4])
    n_data = int((bank.mode != 4).sum())
    assert sorted(bank.embed_pool.tolist()) == list(range(n_data))  # not the taught behaviour
    w = trained.demo_windows((tmp_path / "demo", 0), segments=None)
    assert len(rehearsal) == len(w.actions) == n_demo
    with torch.no_grad():
        frames = {k: f[rehearsal.obs_idx] for k, f in rehearsal.frames.items()}
        torch.testing.assert_close(trained.model.obs_cond(frames), w.obs_cond)
    torch.testing.assert_close(rehearsal.actions[rehearsal.act_idx], w.actions)
    assert torch.equal(rehearsal.is_pad, w.is_pad) and bool((rehearsal.rows == n_data).all())

    seen = []
    trained.model.denoiser.register_forward_hook(lambda m, args, out: seen.append(args[3].detach().clone()))
    trained.train()
    batch = training_batch(synthetic_meta, trained, n=12, episodes=list(range(20)))
    loss, out = trained.forward(batch)
    z = seen[-1]
    assert z.shape[0] == 12 + 4  # 4 taught windows: a quarter of the 16
    torch.testing.assert_close(z[12:], trained.mode_latents()[4].expand(4, -1))
    assert np.isfinite(out["loss_dp_taught"]) and out["loss_dp_taught"] > 0
    loss.backward()
    trained.save_pretrained(tmp_path / "trained")
    assert (tmp_path / "trained" / TAUGHT_DEMOS).is_file()
    again = PDPPolicy.from_pretrained(tmp_path / "trained")
    assert sorted(again.mode_latents()) == [0, 1, 2, 3, 4] and again.config.mode_names["4"] == "far right"
    assert sorted(again.model.bank.taught_demos) == [4]
    assert load_to_train(tmp_path / "trained").model.rehearsal is not None  # --resume: rehearsed on

    # over a grown dataset (more episodes of the same modes): the taught mode joins its behaviours, same id and latent
    caplog.clear()
    cfg = PDPConfig.from_pretrained(tmp_path / "taught")
    cfg.pretrained_path, cfg.dataset_episodes = tmp_path / "taught", None
    grown = make_policy(cfg, ds_meta=synthetic_meta)
    assert "its taught mode(s) 4 ('far right') join them, rehearsed in every batch" in caplog.text
    gb = grown.model.bank
    assert len(gb.episode) == int((gb.mode != 4).sum()) + 1 > len(bank.episode) and gb.distances.shape[0] == len(gb.episode)
    torch.testing.assert_close(grown.mode_latents()[4], taught.mode_latents()[4])
    assert grown.config.mode_names["4"] == "far right" and len(grown.model.rehearsal) == n_demo
    assert int(grown.model.rehearsal.rows[0]) == len(gb.episode) - 1

    # over a dataset without the last training mode: the taught mode keeps its id all the same
    from lerobot_pdp.checkpoint import keep_training_behaviors

    read = grown.model.bank.snapshot()
    read = {k: v if v.dim() == 0 else v[:-1, :-1] if k == "distances" else v[:-1] for k, v in read.items()
            if k != "taught"}  # the grown dataset's own behaviours
    read["taught"] = torch.zeros(0, trained.config.latent_dim)
    keep = torch.nonzero(read["mode"] != 3).flatten()
    fewer = {k: v if v.dim() == 0 or k == "taught" else v[keep][:, keep] if k == "distances" else v[keep]
             for k, v in read.items()}
    loaded = PDPPolicy.from_pretrained(tmp_path / "taught")
    keep_training_behaviors(loaded, fewer, str(tmp_path / "taught" / "model.safetensors"))
    assert loaded.model.bank.taught_modes() == [4] and sorted(loaded.mode_latents()) == [0, 1, 2, 4]

    # over a dataset whose mode labels take the taught id: dropped, saying why and the way back
    read["mode"][0] = 4
    caplog.clear()
    loaded = PDPPolicy.from_pretrained(tmp_path / "taught")
    keep_training_behaviors(loaded, read, str(tmp_path / "taught" / "model.safetensors"))
    assert ("its taught mode(s) 4 ('far right') are dropped (this dataset's mode labels reach 4, which takes their ids; "
            f"teach them to the trained checkpoint again from the demonstrations {tmp_path / 'taught'} keeps"
            in caplog.text)
    assert loaded.model.bank.taught_modes() == [] and not loaded.model.bank.taught_in_training

    (tmp_path / "bare").mkdir()  # a taught checkpoint without its demonstrations: kept, said not rehearsed
    for f in (tmp_path / "taught").iterdir():
        if f.name != TAUGHT_DEMOS:
            (tmp_path / "bare" / f.name).write_bytes(f.read_bytes())
    caplog.clear()
    bare = load_to_train(tmp_path / "bare")
    assert bare.model.rehearsal is None and sorted(bare.mode_latents()) == [0, 1, 2, 3, 4]
    assert "taught mode(s) [4]: their checkpoint keeps no demonstration of them" in caplog.text


def test_lerobot_train_from_a_taught_checkpoint_keeps_its_mode(synthetic_meta, tmp_path):
    """A real ``lerobot-train --policy.path=TAUGHT`` on the training dataset says it rehearses the taught mode, and its
    checkpoint keeps the mode (latent, name, demonstration): ``--policy.steer_mode`` still reaches it."""
    from conftest import lerobot_cli, run_cli
    from lerobot.policies.factory import make_pre_post_processors

    base = tmp_path / "base"
    policy = small_policy(synthetic_meta)
    policy.save_pretrained(base)
    for processor in make_pre_post_processors(policy.config, dataset_stats=synthetic_meta.stats):
        processor.save_pretrained(base)  # as lerobot-train saves a checkpoint
    _write_demo(tmp_path / "demo", new_route())
    assert cli(["teach", str(base), "--demo", str(tmp_path / "demo"), "--data", str(synthetic_meta.root), "--steps",
                "1", "--name", "far right", "--out", str(tmp_path / "taught")]) == 0
    proc = run_cli([lerobot_cli("lerobot-train"), f"--policy.path={tmp_path / 'taught'}", "--dataset.repo_id=local/tiny",
                    f"--dataset.root={synthetic_meta.root}", "--steps=2", "--batch_size=6", "--num_workers=0",
                    "--save_freq=2", "--log_freq=1", "--wandb.enable=false", f"--output_dir={tmp_path / 'train'}"],
                   timeout=600)
    assert "training rehearses taught mode(s) [4]" in proc.stdout + proc.stderr
    trained = PDPPolicy.from_pretrained(tmp_path / "train" / "checkpoints" / "last" / "pretrained_model")
    assert sorted(trained.mode_latents()) == [0, 1, 2, 3, 4] and trained.config.mode_names["4"] == "far right"
    assert sorted(trained.model.bank.taught_demos) == [4]
    torch.testing.assert_close(trained.mode_latents()[4], PDPPolicy.from_pretrained(tmp_path / "taught").mode_latents()[4])


def test_a_policy_trained_without_mode_labels_is_taught_a_mode_past_its_clusters(tmp_path, caplog):
    """Without labels the training modes are the clusters ``mode_latents()`` discovers; a taught mode gets the id past
    them (and past the modes taught before), joins no cluster, and is steered, named, mapped and saved like the
    others."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from lerobot_pdp.latent_map import latent_map_figure

    unlabeled = write_dataset(tmp_path / "unlabeled", episodes_per_mode=3, task="go to the goal")
    q = small_policy(LeRobotDatasetMetadata("local/synthetic", root=unlabeled))
    before = q.discover_modes()
    first = q.teach(new_route(), unlabeled, steps=2, name="far right")
    second = q.teach(new_route(-1.7), unlabeled, steps=1, name="far left")
    assert (first.mode, second.mode) == (before.k, before.k + 1)
    found = q.discover_modes()
    assert found.k == before.k and found.labels == before.labels  # the clusters are the training episodes' alone
    modes = q.mode_latents()
    assert modes.discovered and sorted(modes) == list(range(before.k + 2))
    torch.testing.assert_close(modes[first.mode], first.z[0])
    torch.testing.assert_close(modes["far left"], second.z[0])
    fig = latent_map_figure(q).figure
    legend = " ".join(t.get_text() for t in fig.axes[0].get_legend().get_texts())
    assert f"mode {first.mode}, taught: far right" in legend and f"mode {second.mode}, taught: far left" in legend
    import matplotlib.pyplot as plt

    plt.close(fig)
    q.save_pretrained(tmp_path / "taught")
    again = PDPPolicy.from_pretrained(tmp_path / "taught")
    assert sorted(again.mode_latents()) == sorted(modes) and sorted(again.model.bank.taught_demos) == sorted(
        [first.mode, second.mode])
    third = again.teach(new_route(1.9), unlabeled, steps=1, name="farthest right")
    assert third.mode == before.k + 2 and third.rehearsal_windows > first.rehearsal_windows
    # saved from Python, a taught policy says where its modes came from as `lerobot-pdp teach` does
    info = json.loads((tmp_path / "taught" / TEACHING_INFO).read_text())
    assert (info["mode"], info["mode_name"], info["base_checkpoint"]) == (second.mode, "far left", None)
    assert info["demonstration"] == {"arrays": "given in memory"} and info["training_data"] == str(unlabeled.resolve())
    assert [t["mode_name"] for t in info["earlier_teachings"]] == ["far right"] and info["loss_window"] == 1
    again.save_pretrained(tmp_path / "taught3")
    info3 = json.loads((tmp_path / "taught3" / TEACHING_INFO).read_text())
    assert info3["mode_name"] == "farthest right" and info3["base_checkpoint"] == str((tmp_path / "taught").resolve())
    assert [t["mode"] for t in info3["earlier_teachings"]] == [first.mode, second.mode]
    # the steer CLI takes a cluster's id and a taught mode's name (no labels: the policy's modes are not known to it)
    steer = ["steer", str(tmp_path / "steer.json"), "--policy-path", str(tmp_path / "taught"), "--mode"]
    assert cli([*steer, str(before.k - 1)]) == 0 and cli([*steer, "far left"]) == 0


def test_training_further_on_unlabelled_data_keeps_taught_modes_past_its_clusters(tmp_path, caplog):
    """Trained further (``lerobot-train --policy.path``) on another dataset without labels, a taught checkpoint keeps
    its taught modes where the clusters discovered in that dataset leave their ids free (more episodes of the same
    routes), and drops them saying why where the clusters take them (more routes)."""
    import logging

    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    from lerobot_pdp import PDPConfig

    two = write_dataset(tmp_path / "two", episodes_per_mode=3, modes=(0, 1), task="go to the goal")
    q = small_policy(LeRobotDatasetMetadata("local/synthetic", root=two))
    assert q.teach(new_route(), two, steps=1, name="far right").mode == q.discover_modes().k == 2
    q.save_pretrained(tmp_path / "taught")

    def train_on(root):
        cfg = PDPConfig.from_pretrained(tmp_path / "taught")
        cfg.pretrained_path = tmp_path / "taught"
        return make_policy(cfg, ds_meta=LeRobotDatasetMetadata("local/synthetic", root=root))

    caplog.set_level(logging.INFO, logger="lerobot_pdp")
    more = train_on(write_dataset(tmp_path / "more", episodes_per_mode=5, modes=(0, 1), seed=1, task="go"))
    assert "its taught mode(s) 2 ('far right') join them, rehearsed in every batch" in caplog.text
    assert more.model.bank.taught_modes() == [2] and more.model.rehearsal is not None
    modes = more.mode_latents()
    assert modes.discovered and sorted(modes) == [0, 1, 2] and more.config.mode_names["2"] == "far right"
    torch.testing.assert_close(modes["far right"], q.mode_latents()[2])

    caplog.clear()
    four = train_on(write_dataset(tmp_path / "four", episodes_per_mode=3, task="go"))
    assert ("its taught mode(s) 2 ('far right') are dropped (this dataset has no mode labels, and the 4 clusters "
            "discovered in it take ids up to 3, theirs among them; teach them" in caplog.text)
    assert four.model.bank.taught_modes() == [] and four.model.rehearsal is None and four.discover_modes().k == 4
    assert sorted(more.model.bank.teachings) == [2] and four.model.bank.teachings == {}
    four.save_pretrained(tmp_path / "taught")  # a folder reused: the dropped mode's demonstration and record go
    assert not (tmp_path / "taught" / TEACHING_INFO).exists() and not (tmp_path / "taught" / TAUGHT_DEMOS).exists()


def test_a_taught_and_adapted_checkpoint_loads_from_the_hub(synthetic_meta, tmp_path):
    """A checkpoint pushed to the Hub acts as its folder does: loaded by repo id from the Hub cache (offline, as on
    a robot that downloaded it), it has its taught mode's name, the demonstration it keeps and its adaptation."""
    import os
    import shutil
    import subprocess
    import sys

    base = tmp_path / "base"
    small_policy(synthetic_meta).save_pretrained(base)
    demo = tmp_path / "demo"
    _write_demo(demo, new_route())
    assert cli(["teach", str(base), "--demo", str(demo), "--data", str(synthetic_meta.root), "--steps", "1",
                "--name", "far right", "--out", str(tmp_path / "taught")]) == 0
    config = tmp_path / "taught" / "config.json"
    saved = json.loads(config.read_text())
    assert saved["use_adaptation"] is True  # as the base: teaching's own unadapted load is not saved
    config.write_text(json.dumps({**saved, "use_adaptation": False}))  # as an earlier release saved a taught one
    assert cli(["adapt", str(tmp_path / "taught"), "--demo", str(demo), "--steps", "2", "--out",
                str(tmp_path / "adapted")]) == 0
    assert json.loads((tmp_path / "adapted" / "config.json").read_text())["use_adaptation"] is True
    commit = "0123456789abcdef0123456789abcdef01234567"  # huggingface_hub's cache layout of repo lab/pdp-taught
    repo = tmp_path / "hub" / "models--lab--pdp-taught"
    shutil.copytree(tmp_path / "adapted", repo / "snapshots" / commit)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)

    script = ("import json; from lerobot_pdp import PDPPolicy; p = PDPPolicy.from_pretrained({!r}); "
              "print(json.dumps({{'modes': sorted(p.mode_latents()), 'name': p.config.mode_names['4'], "
              "'taught': sorted(p.model.bank.taught_demos), 'latent': p.active_latent.tolist()}}))")
    env = {**os.environ, "HF_HUB_CACHE": str(tmp_path / "hub"), "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    got = []
    for source in ("lab/pdp-taught", str(tmp_path / "adapted")):
        proc = subprocess.run([sys.executable, "-c", script.format(source)], capture_output=True, text=True, env=env,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        got.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    hub, local = got
    assert hub == local and hub["modes"] == [0, 1, 2, 3, 4] and hub["name"] == "far right" and hub["taught"] == [4]
    adapted = json.loads((tmp_path / "adapted" / "adaptation.json").read_text())
    np.testing.assert_allclose(np.array(hub["latent"]).reshape(-1), np.array(adapted["latent"]).reshape(-1), atol=1e-6)


def _write_demo(root, arrays: dict[str, np.ndarray], *more: dict[str, np.ndarray]) -> None:
    """A LeRobotDataset with one episode per demonstration given."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {k: {"dtype": "float32", "shape": (v.shape[1],), "names": None} for k, v in arrays.items()}
    ds = LeRobotDataset.create(repo_id="local/demo", fps=10, features=features, root=root, use_videos=False)
    for episode in (arrays, *more):
        for t in range(len(episode["action"])):
            ds.add_frame({**{k: v[t] for k, v in episode.items()}, "task": "new route"})
        ds.save_episode()
    ds.finalize()


def test_several_routes_recorded_together_are_taught_in_one_command(synthetic_meta, tmp_path, capsys, monkeypatch):
    """`teach --episode 0 1 --name A B`: one new mode per episode, in order, each rehearsing the one before, into one
    checkpoint; the training dataset is read once. Names and episodes are checked before anything loads."""
    from lerobot_pdp import teaching

    base = tmp_path / "base"
    small_policy(synthetic_meta).save_pretrained(base)
    routes = tmp_path / "routes"
    _write_demo(routes, new_route(), new_route(x_via=-1.7))
    reads = []
    check = teaching.check_training_data
    monkeypatch.setattr(teaching, "check_training_data", lambda *a: reads.append(a) or check(*a))
    args = ["teach", str(base), "--demo", str(routes), "--data", str(synthetic_meta.root), "--steps", "1"]
    assert cli([*args, "--episode", "0", "1", "--name", "far right", "far left", "--out", str(tmp_path / "t")]) == 0
    out = capsys.readouterr().out
    assert "episode 0: mode 4" in out and "episode 1: mode 5" in out and "taught mode(s) 4, 5" in out
    assert len(reads) == 1
    taught = PDPPolicy.from_pretrained(tmp_path / "t")
    assert taught.config.mode_names["4"] == "far right" and taught.config.mode_names["5"] == "far left"
    np.testing.assert_allclose(taught.model.bank.taught_demos[5].arrays["action"], new_route(x_via=-1.7)["action"],
                               atol=1e-6)
    info = json.loads((tmp_path / "t" / TEACHING_INFO).read_text())
    assert info["demonstration"]["episode"] == 1 and info["earlier_teachings"][0]["demonstration"]["episode"] == 0
    assert info["rehearsal_windows"] == info["earlier_teachings"][0]["rehearsal_windows"] + len(new_route()["action"])
    card = (tmp_path / "t" / "README.md").read_text()  # the card names both teachings, not the last one only
    assert "learned 2 demonstrations, a new mode each" in card
    assert "- mode 4 (far right)" in card and "episode 0 of `routes`" in card
    assert "- mode 5 (far left)" in card and "episode 1 of `routes`" in card

    for extra, msg in ((["--episode", "0", "1", "--name", "a"], "--name gives 1 name(s) for 2 --episode(s)"),
                       (["--episode", "1", "1"], "--episode 1 1 repeats an episode"),
                       (["--episode", "0", "1", "--name", "a", "a"], "mode names ['a', 'a'] repeat a name"),
                       (["--episode", "0", "7"], "no episode 7")):  # named before the first teaching
        assert cli([*args, *extra, "--out", str(tmp_path / "x")]) == 2
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_teach_interrupted_or_failed_leaves_the_policy_as_it_was(synthetic_meta, monkeypatch, caplog):
    """Ctrl-C in a notebook (or a non-finite loss) midway through ``teach``: no half-taught mode, no partly
    fine-tuned weights, nothing missing from what was taught before; the same teaching then runs as if it never
    started."""
    from lerobot_pdp import teaching

    p = small_policy(synthetic_meta)
    p.teach(new_route(1.6), synthetic_meta.root, steps=2, seed=0, name="far right")
    modes, names = {m: z.clone() for m, z in p.mode_latents().items()}, dict(p.config.mode_names)
    den, bank, demos = _params(p.model.denoiser), p.model.bank.snapshot(), dict(p.model.bank.taught_demos)
    loss, calls = teaching.diffusion_loss, []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return loss(*args, **kwargs)

    monkeypatch.setattr(teaching, "diffusion_loss", interrupted)
    with caplog.at_level("WARNING", logger="lerobot_pdp.teaching"), pytest.raises(KeyboardInterrupt):
        p.teach(new_route(-1.7), synthetic_meta.root, steps=5, seed=0, name="far left")
    assert "the policy is as it was before teach" in caplog.text
    assert sorted(p.mode_latents()) == sorted(modes) and p.config.mode_names == names
    for k, v in den.items():
        assert torch.equal(p.model.denoiser.state_dict()[k], v), k
    assert p.model.bank.same_behaviors(p.model.bank.snapshot(), bank)
    assert torch.equal(p.model.bank.taught, bank["taught"]) and p.model.bank.taught_demos == demos

    monkeypatch.setattr(teaching, "diffusion_loss", lambda *a, **k: loss(*a, **k) * float("nan"))
    with pytest.raises(FloatingPointError, match="non-finite at step 1 .* the policy is left as it was before teach"):
        p.teach(new_route(-1.7), synthetic_meta.root, steps=5, seed=0, name="far left")
    assert sorted(p.mode_latents()) == sorted(modes)
    monkeypatch.setattr(teaching, "diffusion_loss", loss)
    assert p.teach(new_route(-1.7), synthetic_meta.root, steps=2, seed=0, name="far left").mode == max(modes) + 1


def test_teach_refuses_bad_inputs_by_name(synthetic_meta, tmp_path, capsys):
    p = small_policy(synthetic_meta)
    other = write_dataset(tmp_path / "other", episodes_per_mode=2, seed=5)
    with pytest.raises(ValueError, match=r"other is not the policy's training dataset: it holds 8 behaviours"):
        p.teach(new_route(), other)
    with pytest.raises(FileNotFoundError, match="is not a LeRobotDataset"):
        p.teach(new_route(), tmp_path / "nowhere")
    demo = new_route()
    with pytest.raises(KeyError, match="missing 'observation.environment_state'"):
        p.teach({k: v for k, v in demo.items() if k != "observation.environment_state"}, synthetic_meta.root)
    with pytest.raises(ValueError, match="shorter than one action chunk"):
        p.teach({k: v[:5] for k, v in demo.items()}, synthetic_meta.root)
    with pytest.raises(ValueError, match=r"steps must be a positive integer.*demo_share must be in \(0, 1\]"):
        p.teach(demo, synthetic_meta.root, steps=0, demo_share=1.5)
    assert len(p.mode_latents()) == 4  # nothing half-done

    p.model.bank.mode[0] = -1  # some episodes labelled, some not
    with pytest.raises(ValueError, match="teach needs every training episode mode-labelled, or none"):
        p.teach(demo, synthetic_meta.root)
    p.model.bank.mode[0] = 0

    base = tmp_path / "base"
    p.save_pretrained(base)
    (tmp_path / "taken").mkdir()
    args = ["teach", str(base), "--demo", str(synthetic_meta.root), "--data", str(synthetic_meta.root)]
    assert cli([*args, "--out", str(tmp_path / "taken")]) == 2
    assert "taken exists" in capsys.readouterr().err
    assert cli([*args, "--out", str(base / "taught")]) == 2  # it would copy itself in: refused before any work
    assert f"{base / 'taught'} lies inside the checkpoint {base}" in capsys.readouterr().err
    assert not (base / "taught").exists()
    # refused before the checkpoint loads, each named once ("lerobot-pdp teach: error: ...", no "teach: " again)
    for extra, said in ((["--name", "3"], "error: mode name '3' reads as a mode id (--policy.steer_mode=3 steers to "
                                          "the mode of that id)"),
                        (["--demo", str(tmp_path / "nowhere")], f"error: recording {tmp_path / 'nowhere'} does not exist")):
        assert cli([*args, *extra, "--out", str(tmp_path / "t")]) == 2
        assert f"lerobot-pdp teach: {said}" in capsys.readouterr().err
    with pytest.raises(ValueError, match="mode name '7' reads as a mode id"):
        p.teach(demo, synthetic_meta.root, steps=1, name="7")
    assert cli(["teach", str(base), "--demo", str(synthetic_meta.root), "--out", str(tmp_path / "t")]) == 2
    assert "has no train_config.json naming its training dataset" in capsys.readouterr().err
    (base / "train_config.json").write_text(json.dumps({"dataset": {"root": str(tmp_path / "moved")}}))
    assert cli(["teach", str(base), "--demo", str(synthetic_meta.root), "--out", str(tmp_path / "t")]) == 2
    assert (f"{base / 'train_config.json'} names the training dataset {tmp_path / 'moved'}, which is not here"
            in capsys.readouterr().err)
    (base / "train_config.json").unlink()
    import shutil

    wrong = Path(shutil.copytree(synthetic_meta.root, tmp_path / "wrong"))
    info = json.loads((wrong / "meta" / "info.json").read_text())
    info["features"]["observation.state"]["shape"] = [3]
    (wrong / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"training dataset .*wrong does not match the checkpoint: 'observation.state' "
                                         r"has shape \(3,\).* Give the dataset the policy was trained on \(--data\)"):
        p.teach(new_route(), wrong)
    assert not (tmp_path / "t").exists()
    # an adapted checkpoint saved from Python (it names no base): its weights are taught, the result acts unadapted
    p.fit_latent((synthetic_meta.root, 1), steps=1)
    p.save_pretrained(tmp_path / "adapted")
    assert cli(["teach", str(tmp_path / "adapted"), *args[2:], "--steps", "1", "--name", "x",
                "--out", str(tmp_path / "t")]) == 0
    assert not (tmp_path / "t" / "adaptation.json").exists() and "## Adaptation" not in (tmp_path / "t" / "README.md").read_text()
    assert len(PDPPolicy.from_pretrained(tmp_path / "t").active_latent) == 0


def test_a_latent_placed_by_the_geometry_is_kept_with_the_checkpoint(synthetic_meta, tmp_path):
    """``latent="geometry"``: the new mode's latent satisfies the encoder's geometry term against the fixed training
    latents better than the encoder's own latent does; the bank keeps it (mode_latents, save / load)."""
    from lerobot_pdp.teaching import geometric_latent

    p = small_policy(synthetic_meta)
    z_old = p.behavior_latents().detach()
    demo = new_route()
    res = p.teach(demo, synthetic_meta.root, steps=1, latent="geometry")
    bank = p.model.bank
    delta = bank.distances[-1:, :-1]

    def stress(z):
        return float(((torch.cdist(z, z_old) - bank.kappa * delta) ** 2).mean())

    z_enc = p.encode(demo)[None]
    assert stress(res.z) < stress(z_enc) and not torch.allclose(res.z, z_enc)
    torch.testing.assert_close(p.mode_latents()[4], res.z[0])
    torch.testing.assert_close(geometric_latent(z_enc, z_old, delta, float(bank.kappa)), res.z)
    p.save_pretrained(tmp_path / "taught")
    q = PDPPolicy.from_pretrained(tmp_path / "taught")
    torch.testing.assert_close(q.mode_latents()[4], res.z[0])
    torch.testing.assert_close(q.behavior_latents(), p.behavior_latents())
    with pytest.raises(ValueError, match="latent must be one of"):
        p.teach(demo, synthetic_meta.root, steps=1, latent="far")


def test_a_used_mode_name_and_a_known_route_are_named_before_the_fine_tuning(synthetic_meta, caplog):
    """A name an old mode has would make steering by name reach the old mode: refused. A demonstration of a
    route the policy already has (a training episode) is taught, with a warning that a fit would do."""
    import logging

    from lerobot_pdp.steering import apply_steering

    from synthetic import MODES

    p = small_policy(synthetic_meta)
    with pytest.raises(ValueError, match=rf"mode 1 is already named '{MODES[1][0]}'; give the new mode another name"):
        p.teach(new_route(), synthetic_meta.root, steps=1, name=MODES[1][0])
    assert len(p.mode_latents()) == 4
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.teaching"):
        p.teach(new_route(), synthetic_meta.root, steps=1, name="far right")
    assert "may know this route already" not in caplog.text  # a route of its own
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.teaching"):
        res = p.teach((synthetic_meta.root, 5), synthetic_meta.root, steps=1, name="episode 5 again")
    mode5 = int(p.model.bank.mode[p.model.bank.episode == 5][0])
    assert f"close to training episode 5 (mode {mode5})" in caplog.text and f"teaching mode {res.mode}" in caplog.text
    p.config.mode_names[str(res.mode)] = "far right"  # as a checkpoint taught before names were checked holds them
    with pytest.raises(KeyError, match=r"mode name 'far right' names modes \[4, 5\]; steer by mode id"):
        apply_steering(p, {"mode": "far right"})
    from lerobot_pdp.steer_requests import SteerTarget, check_request

    target = SteerTarget(latent_dim=2, modes={int(k): v for k, v in p.config.mode_names.items()}, source="checkpoint C",
                         latent_source="its config")
    with pytest.raises(ValueError, match=r"mode name 'far right' names modes \[4, 5\] in checkpoint C; steer by mode id"):
        check_request({"mode": "far right"}, target)


def test_the_teaching_record_names_a_lerobot_dataset_by_its_folder(synthetic_meta):
    """A demonstration given as (LeRobotDataset, index) is recorded as the dataset's folder, as adaptation.json
    records it (the repr of the dataset object was written as a path)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_pdp.teaching import TeachResult, teaching_record

    ds = LeRobotDataset("local/synthetic", root=synthetic_meta.root, video_backend="pyav")
    record = teaching_record(small_policy(synthetic_meta), (ds, 2), Path(synthetic_meta.root),
                             TeachResult(mode=4, z=torch.zeros(1, 2), losses=[1.0, 0.5], steps=2), "far right")
    assert record["demonstration"] == {"dataset": str(Path(synthetic_meta.root).resolve()), "episode": 2}
