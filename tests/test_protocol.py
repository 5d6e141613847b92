"""The evaluation protocol end to end (real lerobot-train, real MuJoCo rollouts) and PDP's steering effect."""

import json

import numpy as np
import pytest
from conftest import lerobot_cli, run_cli

from lerobot_pdp.benchmark.data import demo_episode, ensure_demo
from lerobot_pdp.benchmark.protocol import run_benchmark
from lerobot_pdp.benchmark.settings import BenchmarkConfig
from lerobot_pdp.benchmark.training import load_policy, load_run
from lerobot_pdp.envs import get_suite_env

pytestmark = pytest.mark.slow


def test_whole_protocol_tiny(tmp_path):
    """Every stage on a tiny budget: dataset, 3 methods trained by lerobot-train, scenes 0-3, tables, figures."""
    # 4 sampler steps instead of the env's 20: DP's noise adaptation backpropagates through every step
    cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "bench", seeds=[0], rollouts=2,
                          methods=["pdp", "dp", "bc"], steps=20, episodes_per_mode=1, inference_steps=4)
    res = run_benchmark(cfg)
    saved = json.loads((tmp_path / "bench" / "results.json").read_text())
    assert saved["env"] == "reach-around" and saved["rollouts"] == 2 and saved["seeds"] == [0]
    for m in ("pdp", "dp", "bc"):
        for s in range(4):
            entry = saved["methods"][m][f"scene{s}"]
            assert len(entry["success"]) == 1 and entry["mean"] == entry["success"][0]
    assert "coverage" in saved["methods"]["pdp"]["scene0"]
    assert "| pdp |" in (tmp_path / "bench" / "results.md").read_text()
    figs = {p.split("/")[-1] for p in res["figures"]}
    assert {"latent_map_pdp.png", "rollouts_xy.png", "interpolation.png"} <= figs
    out = tmp_path / "bench"
    # paths relative to the output folder (it can be moved or committed); the sweep is a cached result too
    assert all((out / p).is_file() and not p.startswith("/") for p in saved.get("figures", res["figures"]))
    info = json.loads((out / "runs" / "pdp" / "seed0" / "train_info.json").read_text())
    assert info["args"][0] == "lerobot-train" and not any(a.partition("=")[2].startswith("/") for a in info["args"])
    assert "--dataset.root=../../../data/reach_around_scene0" in info["args"]
    assert info["column_views"] is True  # the pinned LeRobot 0.6.1 trains with single-column loading
    sweep = json.loads((out / "runs" / "pdp" / "seed0" / "sweep.json").read_text())
    assert set(sweep["paths"]) == {"linear", "elliptical"} and len(sweep["paths"]["linear"]["rollouts"]) == 7
    assert [_eval_json(out, m)["inference_steps"] for m in ("pdp", "dp", "bc")] == [4, 4, None]
    for m in ("dp", "pdp"):  # the env's sampler is written into the checkpoints, so lerobot-eval uses it too
        saved_cfg = json.loads((out / "runs" / m / "seed0" / "pretrained_model" / "config.json").read_text())
        assert saved_cfg["num_inference_steps"] == 20
    # and PDP's its share of the sampler DP has (diffusers' DDIM on the env's grid, LeRobot's step rule)
    assert (saved_cfg["timestep_spacing"], saved_cfg["use_clipped_model_output"]) == ("leading", False)
    # resumable: a rerun reuses every trained checkpoint and cached evaluation; an eval.json from before
    # the "inference_steps" key existed counts as made with the checkpoint's own DDIM steps (here 20)
    stamps = {m: (out / "runs" / m / "seed0" / "train_info.json").stat().st_mtime for m in ("pdp", "dp", "bc")}
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "figures": False}))
    legacy = _eval_json(out, "pdp")
    del legacy["inference_steps"]
    (out / "runs" / "pdp" / "seed0" / "eval.json").write_text(json.dumps(legacy))
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["pdp"], "figures": False, "inference_steps": None}))
    assert _eval_json(out, "pdp") == legacy
    # --inference-steps (from the CLI): evaluations made with other steps are redone, checkpoints reused
    proc = run_cli([lerobot_cli("lerobot-pdp"), "benchmark", "--env", "reach-around", "--out", str(out), "--seeds", "0",
                    "--rollouts", "2", "--methods", "pdp", "dp", "bc", "--steps", "20", "--episodes-per-mode", "1",
                    "--no-figures", "--inference-steps", "2"])
    assert "DDIM sampler steps (grid): pdp 2 (leading), dp 2 (leading)." in proc.stdout
    res = json.loads((out / "results.json").read_text())
    assert [_eval_json(out, m)["inference_steps"] for m in ("pdp", "dp", "bc")] == [2, 2, None]
    assert res["methods"]["pdp"]["inference_steps"] == [2] and "inference_steps" not in res["methods"]["bc"]
    assert stamps == {m: (out / "runs" / m / "seed0" / "train_info.json").stat().st_mtime for m in stamps}
    policy, _, _ = load_policy(out / "runs" / "dp" / "seed0" / "pretrained_model", inference_steps=3)
    assert policy.diffusion.num_inference_steps == 3
    policy, _, _ = load_run(out / "runs" / "dp" / "seed0")  # as its eval.json was made
    assert policy.diffusion.num_inference_steps == 2
    with pytest.raises(ValueError, match=r"inference_steps=21 .*expected 1\.\.20"):
        load_policy(out / "runs" / "pdp" / "seed0" / "pretrained_model", inference_steps=21)
    # one grid for both methods: DP's scheduler is rebuilt with it, PDP's sampler follows its config
    dp, _, _ = load_policy(out / "runs" / "dp" / "seed0" / "pretrained_model", 5, timestep_spacing="trailing")
    dp.diffusion.noise_scheduler.set_timesteps(5)
    pdp, _, _ = load_policy(out / "runs" / "pdp" / "seed0" / "pretrained_model", 5, timestep_spacing="trailing")
    assert dp.diffusion.noise_scheduler.timesteps.tolist() == pdp.model.noise_schedule.timesteps(5) == [19, 15, 11, 7, 3]
    assert not pdp.model.noise_schedule.use_clipped_model_output
    with pytest.raises(ValueError, match="PDP's own sampler"):
        load_policy(out / "runs" / "dp" / "seed0" / "pretrained_model", timestep_spacing="even")
    # --timestep-spacing re-evaluates like --inference-steps, recorded per evaluation
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["pdp"], "figures": False, "inference_steps": 2,
                                     "timestep_spacing": "trailing"}))
    assert _eval_json(out, "pdp")["timestep_spacing"] == "trailing"
    assert json.loads((out / "results.json").read_text())["methods"]["pdp"]["timestep_spacing"] == ["trailing"]
    # an evaluation cut short after two scenes goes on from the third: the finished scenes are kept as they are
    bc_dir = out / "runs" / "bc" / "seed0"
    full = _eval_json(out, "bc")
    cut = {**full, "scenes": {k: full["scenes"][k] for k in ("0", "1")}}
    (bc_dir / "eval.json").write_text(json.dumps(cut))
    traces = json.loads((bc_dir / "traces.json").read_text())
    (bc_dir / "traces.json").write_text(json.dumps({k: traces[k] for k in ("0", "1")}))
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["bc"], "figures": False}))
    resumed = _eval_json(out, "bc")
    assert list(resumed["scenes"]) == ["0", "1", "2", "3"]
    assert all(resumed["scenes"][k] == full["scenes"][k] for k in ("0", "1"))  # not re-run
    assert [resumed["scenes"][k]["success"] for k in ("2", "3")] == [full["scenes"][k]["success"] for k in ("2", "3")]
    assert resumed["scenes"]["2"]["seconds"] != full["scenes"]["2"]["seconds"]  # re-run, same seeded outcome
    assert list(json.loads((bc_dir / "traces.json").read_text())) == ["0", "1", "2", "3"]


def test_camera_variant_tiny(tmp_path):
    """benchmark --obs images: camera datasets, PDP, DP and VQ-BeT with the same vision encoder trained by
    lerobot-train on them, DP's noise adaptation, VQ-BeT's fine-tuning and PDP's fit on a camera
    demonstration, camera rollouts."""
    out = tmp_path / "cam"
    proc = run_cli([lerobot_cli("lerobot-pdp"), "benchmark", "--env", "reach-around", "--obs", "images",
                    "--image-size", "40", "--out", str(out), "--seeds", "0", "--rollouts", "2", "--steps", "4",
                    "--episodes-per-mode", "1", "--scenes", "0", "3", "--no-figures", "--inference-steps", "2"])
    assert "camera 'oblique' (40x40) for every method" in proc.stdout
    res = json.loads((out / "results.json").read_text())
    assert res["observation"] == {"obs": "images", "camera": "oblique", "image_size": 40}
    assert set(res["methods"]) == {"pdp", "dp", "vqbet"}
    for m in ("pdp", "dp", "vqbet"):
        assert set(_eval_json(out, m)["scenes"]) == {"0", "3"}
        cfg = json.loads((out / "runs" / m / "seed0" / "pretrained_model" / "config.json").read_text())
        assert cfg["input_features"]["observation.images.oblique"]["shape"] == [3, 40, 40]
        assert cfg["pretrained_backbone_weights"] is None and cfg["use_group_norm"] is True
        assert cfg["spatial_softmax_num_keypoints"] == 32 and cfg["n_obs_steps"] == 2
        assert cfg.get("use_separate_rgb_encoder_per_camera", False) is False
    vq = json.loads((out / "runs" / "vqbet" / "seed0" / "pretrained_model" / "config.json").read_text())
    assert vq["crop_shape"] is None and vq["n_vqvae_training_steps"] == 1  # a fifth of the 4 steps, at least 1
    demo = demo_episode(out / "data" / "reach_around_scene3_demo_oblique40")
    cam = demo["observation.images.oblique"]
    assert cam.shape == (len(demo["action"]), 3, 40, 40) and 0.0 <= cam.min() and cam.max() <= 1.0
    with pytest.raises(AssertionError, match="take state only"):  # BC has no camera input
        run_cli([lerobot_cli("lerobot-pdp"), "benchmark", "--env", "reach-around", "--obs", "images",
                 "--out", str(out), "--methods", "bc"])


def _eval_json(out, method):
    return json.loads((out / "runs" / method / "seed0" / "eval.json").read_text())


def test_ablations_tiny(tmp_path):
    """`--ablations`: the five ablated PDP variants train and evaluate next to PDP, plus the warm-vs-random
    initialisation table."""
    cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "bench", seeds=[0], rollouts=1, methods=["pdp"],
                          ablations=True, steps=20, episodes_per_mode=1, figures=False, inference_steps=4)
    res = run_benchmark(cfg)
    assert set(res["methods"]) == {"pdp", "pdp_unaligned", "pdp_onehot", "pdp_concat", "pdp_input", "pdp_uncond"}
    for entry in res["methods"].values():
        assert all(len(entry[f"scene{s}"]["success"]) == 1 for s in range(4))
    assert set(res["init_ablation"]) == {f"{i}@{n}" for i in ("encoder", "random") for n in (0, 10, 100)}
    for entry in res["init_ablation"].values():  # the mean over shifts 1-3 and each shift's own rate
        assert set(entry["scenes"]) == {"1", "2", "3"}
        assert entry["mean"] == pytest.approx(sum(entry["scenes"].values()) / 3)
    md = (tmp_path / "bench" / "results.md").read_text()
    assert "| pdp_onehot |" in md and "| warm (encoder) |" in md
    config = tmp_path / "bench" / "runs" / "pdp_onehot" / "seed0" / "pretrained_model" / "config.json"
    assert json.loads(config.read_text())["latent_type"] == "onehot"
    # lerobot-train tracked the training error into the checkpoint: every fit is judged against it
    for name in ("pdp", "pdp_input"):
        scenes = _eval_json(tmp_path / "bench", name)["scenes"]
        assert all(scenes[s]["fit_error_ratio"] > 0 and scenes[s]["fit_error"] > 0 for s in ("1", "2", "3"))
    # cached with the sampler it was made with (4 DDIM steps here, to keep the test short), so a rerun reuses it
    init_json = tmp_path / "bench" / "runs" / "pdp" / "seed0" / "init_ablation.json"
    assert json.loads(init_json.read_text())["inference_steps"] == 4
    stamp = init_json.stat().st_mtime
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "ablations": False}))
    assert init_json.stat().st_mtime == stamp


def test_pdp_steers_to_a_new_route_from_one_demo(reach_around_pdp, tmp_path):
    """The steering effect itself (reach-around scene 3: a wall with one window that no training mode uses).

    After fit_latent on ONE scene-3 demonstration PDP succeeds in >= 80 % of 10 rollouts; conditioned on
    any training mode's mean latent it succeeds in <= 20 %.
    """
    from lerobot_pdp.benchmark.rollouts import run_rollouts

    suite = get_suite_env("reach-around")
    ckpt = reach_around_pdp  # 3000 steps, conftest
    policy, pre, post = load_policy(ckpt)
    means = policy.mode_latents()
    baseline = run_rollouts(suite, 3, policy, pre, post, 0, seed=0)
    for m, z in means.items():
        policy.set_latent(z)
        per_mode = run_rollouts(suite, 3, policy, pre, post, 2, seed=100 + m)
        assert per_mode.success_rate <= 0.5, (m, per_mode.success_rate)  # no mode's latent makes the route
        baseline.extend(per_mode)
    assert baseline.success_rate <= 0.2, baseline.success_rate
    demo_root, source = ensure_demo(suite, tmp_path, 3)
    assert "way-points" in source
    res = policy.fit_latent(demo_episode(demo_root))
    assert np.isfinite(res.losses).all()
    fitted = run_rollouts(suite, 3, policy, pre, post, 10, seed=1)
    # the same steering from the command line: lerobot-eval fits z at start-up from the demo dataset
    out = tmp_path / "eval"
    proc = run_cli([lerobot_cli("lerobot-eval"), f"--policy.path={ckpt}", "--env.type=pdp_reach_around",
                    "--env.scene=3", f"--policy.steer_dataset_root={demo_root}", "--policy.steer_episode_index=0",
                    "--policy.device=cpu", "--eval.n_episodes=2", "--eval.batch_size=2", f"--output_dir={out}"])
    assert f"fitted latent to {demo_root} episode 0" in proc.stdout + proc.stderr
    info = json.loads(next(out.rglob("eval_info.json")).read_text())
    # the same fit as above (same demo, settings and seed): the route it opens is taken from the command line too
    assert info["overall"]["n_episodes"] == 2 and info["overall"]["pc_success"] >= 50, info["overall"]
    # fitting z alone turns a scene every training mode fails into a solved one
    assert fitted.success_rate >= 0.8, fitted.success_rate
