"""Per-env method definitions of the benchmark: what each method's lerobot-train call gets."""

import json

import draccus
import pytest

from lerobot_pdp import PDPConfig
from lerobot_pdp.benchmark.settings import SETTINGS, film_form, methods_for
from lerobot_pdp.benchmark.training import train_args, train_method
from lerobot_pdp.envs import get_suite_env


def _pdp_config(overrides: tuple[str, ...]) -> PDPConfig:
    """Parse ``--policy.*`` overrides the way lerobot-train does for ``--policy.type=pdp``."""
    return draccus.parse(PDPConfig, args=["--" + a.removeprefix("--policy.") for a in overrides] + ["--device=cpu"])


def test_pick_place_pdp_uses_an_affine_film_every_other_env_the_defaults():
    """The FiLM form is a training flag; fitting settings are not (they are validated per env in FROZEN), so
    every env trains with PDPConfig's fitting defaults."""
    pick = methods_for(get_suite_env("pick-place"))
    for name in ("pdp", "pdp_unaligned", "pdp_onehot"):  # the ablations vary one thing of the env's PDP
        cfg = _pdp_config(pick[name].overrides)
        assert tuple(cfg.film_hidden_dims) == () and cfg.segment_gripper_dim == 3
    assert not any("film_hidden_dims" in a for m in ("dp", "bc") for a in pick[m].overrides)
    for env in ("reach-around", "avoiding", "kitchen-microwave", "pick-place"):
        cfg = _pdp_config(methods_for(get_suite_env(env))["pdp"].overrides)
        assert cfg.fit_lambda == PDPConfig.fit_lambda > 0 and cfg.fit_steps == PDPConfig.fit_steps
        if env != "pick-place":
            assert tuple(cfg.film_hidden_dims) == (16, 32) and cfg.segment_gripper_dim is None


@pytest.mark.parametrize("env", ["avoiding", "pick-place"])
def test_film_option_trains_pdp_and_its_ablations_with_that_form_only(env):
    """``benchmark --film``: a FiLM form is a training setting compared on the validation split; it changes
    PDP and its ablations, never DP or BC, and the env's other PDP overrides stay."""
    suite = get_suite_env(env)
    for film, dims in (("affine", ()), ("mlp", (16, 32))):
        methods = methods_for(suite, film)
        for name in ("pdp", "pdp_concat"):
            cfg = _pdp_config(methods[name].overrides)
            assert tuple(cfg.film_hidden_dims) == dims
            assert cfg.fit_lambda == PDPConfig.fit_lambda
        for name in ("dp", "bc"):
            assert methods[name].overrides == methods_for(suite)[name].overrides
    # the env's own form is the default, and the same arguments as before the option (cached runs stay reusable)
    assert methods_for(suite, film_form(env)) == methods_for(suite)
    with pytest.raises(ValueError, match="film must be one of"):
        methods_for(suite, "mlp2")


def test_rec_reduction_option_changes_pdp_and_its_ablations_only():
    """``benchmark --rec-reduction sum`` trains PDP with the paper's summed L_rec; "mean" (the default) keeps
    the arguments of every run before the option, so cached runs stay reusable."""
    suite = get_suite_env("reach-around")
    assert methods_for(suite, rec_reduction="mean") == methods_for(suite)
    summed = methods_for(suite, rec_reduction="sum")
    for name in ("pdp", "pdp_unaligned"):
        assert _pdp_config(summed[name].overrides).embed_rec_reduction == "sum"
        assert _pdp_config(methods_for(suite)[name].overrides).embed_rec_reduction == "mean"
    for name in ("dp", "bc"):
        assert summed[name].overrides == methods_for(suite)[name].overrides
    with pytest.raises(ValueError, match="rec_reduction must be one of"):
        methods_for(suite, rec_reduction="median")


def test_a_checkpoint_trained_with_other_arguments_is_not_reused(tmp_path):
    """Resuming into an old --out after the protocol changed (here: the step budget, a method flag) must not
    put the stale run into the new table; the output folder, logging, loader workers and sampler steps may
    differ."""
    method = methods_for(get_suite_env("pick-place"))["pdp"]
    settings, data = SETTINGS["pick-place"][0], tmp_path / "data" / "pick_place_scene0"
    run_dir = tmp_path / "runs" / "pdp" / "seed0"
    (run_dir / "pretrained_model").mkdir(parents=True)
    (run_dir / "pretrained_model" / "model.safetensors").write_bytes(b"")
    # as train_info.json records them: paths relative to the run folder, the bare program name
    recorded = {"--dataset.root": "../../../moved/data", "--num_workers": "0", "--log_freq": "100",
                "--save_freq": "1000", "--policy.num_inference_steps": "5",
                "--policy.device": "cuda"}  # none of these changes the weights
    args = ["lerobot-train"] + [
        next((f"{k}={v}" for k, v in recorded.items() if a.startswith(k + "=")), a)
        for a in train_args(method, data, 0, settings, settings.steps)[1:]
    ] + ["--output_dir=.train-x/out"]
    assert sum(a.split("=")[0] in recorded for a in args) == len(recorded)
    info = run_dir / "train_info.json"
    info.write_text(json.dumps({"seconds": 1.0, "steps": settings.steps, "args": args}))
    assert train_method(method, data, run_dir, 0, settings, settings.steps) == run_dir / "pretrained_model"
    with pytest.raises(ValueError, match=r"seed0 was trained with other lerobot-train arguments \("
                                         r"--policy.scheduler_warmup_steps: trained with 100, now 10; "
                                         rf"--steps: trained with {settings.steps}, now 100\)"):
        train_method(method, data, run_dir, 0, settings, 100)
    info.write_text(json.dumps({"seconds": 1.0, "steps": settings.steps,
                                "args": [a for a in args if "film_hidden_dims" not in a]}))
    with pytest.raises(ValueError, match=r"--policy.film_hidden_dims: trained with \(absent\), now \[\]"):
        train_method(method, data, run_dir, 0, settings, settings.steps)
    info.unlink()  # copied in by hand: reused as it is
    assert train_method(method, data, run_dir, 0, settings, 100) == run_dir / "pretrained_model"


def test_retraining_a_run_drops_its_evaluations_and_a_failed_run_leaves_no_checkpoint(tmp_path, capsys):
    """A run whose checkpoint is gone is trained again: the eval.json / traces.json / init_ablation.json /
    train_info.json of the earlier model must not be taken for this one's. Here lerobot-train (a real process) fails on a missing
    dataset: the error names the log, and neither a checkpoint nor its train_info.json is left behind; a
    partial run of another command found there is discarded with a message."""
    method = methods_for(get_suite_env("reach-around"))["bc"]
    settings = SETTINGS["reach-around"][1]
    run_dir = tmp_path / "runs" / "bc" / "seed0"
    run_dir.mkdir(parents=True)
    for stale in ("eval.json", "traces.json", "init_ablation.json", "sweep.json", "train_info.json"):
        (run_dir / stale).write_text("{}")
    # a partial run of another command (steps 20) is thrown away, and the user is told so
    step_file = run_dir / ".train-partial" / "out" / "checkpoints" / "last" / "training_state" / "training_step.json"
    step_file.parent.mkdir(parents=True)
    step_file.write_text(json.dumps({"step": 10}))
    (run_dir / ".train-partial" / "progress.json").write_text(json.dumps({"args": ["x", "--steps=20"], "seconds": {}}))
    with pytest.raises(RuntimeError, match=r"lerobot-train failed with exit code \d+; see .*train\.log"):
        train_method(method, tmp_path / "no_such_dataset", run_dir, 0, settings, 10)
    assert sorted(p.name for p in run_dir.iterdir()) == ["train.log"]
    assert "discarding a partial training (checkpoint at step 10) made with other lerobot-train arguments" in \
        capsys.readouterr().out


def test_ablations_sample_and_fit_with_pdps_frozen_settings():
    from lerobot_pdp.benchmark.settings import ABLATIONS, frozen_for

    for name in ABLATIONS:
        assert frozen_for("reach-around", False, name) == {"adapt": {"objective": "sample"}}
        assert frozen_for("reach-around", True, name) == {"sampler": [10, "trailing"], "adapt": {"noise": "chunks"}}
        assert frozen_for("reach-around", False, name, obs="images") == {}  # not carried over to cameras
    assert frozen_for("reach-around", False, "dp") == {"sampler": [5, "trailing"]}
    assert frozen_for("kitchen-microwave", False, "pdp_concat") == {"adapt": {"noise": "chunks"}}


def test_frozen_settings_are_what_the_committed_validation_records_chose():
    """settings.FROZEN is copied by hand from validation.json: each entry must equal its record's choice (an
    absent sampler / adaptation = the env's TrainSettings sampler / the defaults), and every frozen
    adaptation keyword must be one the method's adaptation takes (a typo would otherwise fail only when a
    benchmark run reaches that adaptation)."""
    import inspect
    from pathlib import Path

    from lerobot_pdp import PDPPolicy
    from lerobot_pdp.benchmark import settings
    from lerobot_pdp.benchmark.baselines import adapt_dp_noise, finetune_bc
    from lerobot_pdp.benchmark.results import validation_summary

    takes = {"fit_latent": PDPPolicy.fit_latent, "noise": adapt_dp_noise, "finetune": finetune_bc}
    root = Path(__file__).resolve().parents[1]
    assert set(settings.FROZEN) <= set(settings.VALIDATION_RECORDS)
    for (env, budget), rel in settings.VALIDATION_RECORDS.items():
        record = json.loads((root / rel).read_text())
        assert record["env"] == env and record["split"] == "validation"
        full, quick = SETTINGS[env]
        train = quick if budget.startswith("quick") else full
        frozen = settings.FROZEN.get((env, budget), {})
        assert set(frozen) <= set(record["methods"]), (env, budget)
        suite = get_suite_env(env)
        if budget.endswith("+images"):  # the camera variant's methods (vqbet among them)
            suite = suite.with_camera(settings.CAMERAS[env], settings.IMAGE_SIZE)
        methods = methods_for(suite)
        for name, rec in record["methods"].items():
            f, chosen = frozen.get(name, {}), rec["chosen"]
            if chosen["sampler"] is not None:
                assert f.get("sampler", [train.inference_steps, train.timestep_spacing]) == chosen["sampler"], (env, name)
            assert f.get("adapt", {}) == chosen["adapt"], (env, budget, name)
            params = inspect.signature(takes[methods[name].adapt]).parameters
            assert set(f.get("adapt", {})) <= set(params), (env, budget, name, f)
        # results.json carries the same record, summarised: which seeds and scenes chose what
        summary = validation_summary(rel)
        assert {n: m["chosen"] for n, m in summary.items()} == {n: m["chosen"] for n, m in record["methods"].items()}
        assert all(min(m["seeds"]) >= 100 and "0" in m["scenes"] for m in summary.values()), (env, budget)


def test_benchmark_lr_overrides_every_methods_learning_rate(tmp_path):
    """``--lr`` (for choosing defaults on validation) reaches every method's lerobot-train call, PDP's encoder
    too; a non-positive one is refused before anything is trained."""
    from dataclasses import replace

    from lerobot_pdp.benchmark.protocol import run_benchmark
    from lerobot_pdp.cli import benchmark_config, build_parser

    cfg = benchmark_config(build_parser().parse_args(["benchmark", "--env", "reach-around", "--out", "o", "--lr", "1e-4"]))
    assert cfg.lr == 1e-4
    settings = replace(SETTINGS["reach-around"][0], lr=cfg.lr)
    for name, method in methods_for(get_suite_env("reach-around")).items():
        args = train_args(method, tmp_path / "data", 0, settings, 10)
        assert "--policy.optimizer_lr=0.0001" in args, name
        assert ("--policy.embedding_lr=0.0001" in args) == (method.policy_type == "pdp"), name
    with pytest.raises(ValueError, match="lr must be > 0, got 0.0"):
        run_benchmark(replace(cfg, out=tmp_path / "bench", lr=0.0))
    assert not (tmp_path / "bench").exists()


@pytest.mark.parametrize(("argv", "message"), [
    (["--rollouts", "0"], r"rollouts must be a whole number >= 1, got 0"),
    (["--steps", "0"], r"steps must be a whole number >= 1, got 0"),
    (["--steps", "-5"], r"steps must be a whole number >= 1, got -5"),
    (["--seeds", "-1"], r"seeds must be whole numbers in 0..2\*\*32-1 \(lerobot-train's --seed\), got -1"),
    (["--seeds", "0", "0"], r"seeds lists 0 more than once"),
    (["--scenes", "0", "1", "1"], r"scenes lists 1 more than once; each is run \(and counted\) once"),
    (["--scenes", "0", "7"], r"--scenes 7: reach-around ships no such scene"),
])
def test_a_benchmark_request_that_would_report_wrong_numbers_is_refused_before_anything_is_made(tmp_path, argv,
                                                                                                  message):
    from lerobot_pdp.benchmark.protocol import run_benchmark
    from lerobot_pdp.cli import benchmark_config, build_parser

    cfg = benchmark_config(build_parser().parse_args(["benchmark", "--env", "reach-around", "--quick", "--out",
                                                      str(tmp_path / "bench"), *argv]))
    with pytest.raises(ValueError, match=message):
        run_benchmark(cfg)
    assert not (tmp_path / "bench").exists()


def test_benchmark_out_under_a_file_is_named(tmp_path, capsys):
    from lerobot_pdp.cli import main

    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        assert main(["benchmark", "--env", "reach-around", "--quick", "--out", str(out)]) == 2
        assert f"--out {out}: {tmp_path / 'afile'} is a file; give a folder" in capsys.readouterr().err


def test_benchmark_batch_size_overrides_every_methods_batch(tmp_path):
    """``--batch-size`` (for choosing a budget on validation) reaches every method's lerobot-train call; a
    batch below 1 is refused before anything is trained."""
    from dataclasses import replace

    from lerobot_pdp.benchmark.protocol import run_benchmark
    from lerobot_pdp.cli import benchmark_config, build_parser

    cfg = benchmark_config(build_parser().parse_args(["benchmark", "--env", "reach-around", "--quick", "--out", "o",
                                                      "--batch-size", "32"]))
    assert cfg.batch_size == 32
    settings = replace(SETTINGS["reach-around"][1], batch_size=cfg.batch_size)
    for name, method in methods_for(get_suite_env("reach-around")).items():
        assert "--batch_size=32" in train_args(method, tmp_path / "data", 0, settings, 10), name
    with pytest.raises(ValueError, match="batch_size must be >= 1, got 0"):
        run_benchmark(replace(cfg, out=tmp_path / "bench", batch_size=0))
    assert not (tmp_path / "bench").exists()


@pytest.mark.slow
def test_an_interrupted_training_run_resumes_from_its_last_checkpoint(tmp_path):
    """A benchmark training killed from outside (a machine going away) after a checkpoint goes on from that
    checkpoint with lerobot-train's own resume when called again with the same arguments; a partial run
    with other arguments is not resumed. Real lerobot-train processes, killed with SIGKILL as soon as a first
    checkpoint is seen (whichever it is by then: the kill races the trainer, the resume must not)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from lerobot_pdp.benchmark import training
    from lerobot_pdp.benchmark.settings import TrainSettings
    from lerobot_pdp.envs.recording import make_dataset

    data = make_dataset("reach-around", tmp_path / "data", scene=0, episodes_per_mode=1, seed=0, progress=False)
    run_dir, steps, every = tmp_path / "run", 400, 20
    call = (f"training.train_method(methods_for(get_suite_env('reach-around'))['bc'], Path({str(data)!r}), "
            f"Path({str(run_dir)!r}), 0, TrainSettings(steps={steps}, batch_size=8), {steps})")
    code = ("from pathlib import Path\nfrom lerobot_pdp.benchmark import training\n"
            "from lerobot_pdp.benchmark.settings import TrainSettings, methods_for\n"
            f"from lerobot_pdp.envs import get_suite_env\ntraining.RESUME_EVERY = {every}\n{call}\n")
    env = {**os.environ, "LEROBOT_PDP_TRAIN_WORKERS": "0", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.Popen([sys.executable, "-c", code], start_new_session=True, env=env)
    partial = run_dir / ".train-partial"
    step_file = partial / "out" / "checkpoints" / "last" / "training_state" / "training_step.json"
    deadline = time.time() + 600
    while proc.poll() is None and not step_file.exists() and time.time() < deadline:
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)  # the trainer and lerobot-train with it
    proc.wait()
    assert step_file.exists() and not (run_dir / "pretrained_model").exists()
    done = json.loads(step_file.read_text())["step"]
    assert done % every == 0 and every <= done < steps, done

    settings = TrainSettings(steps=steps, batch_size=8)
    args = training.train_args(methods_for(get_suite_env("reach-around"))["bc"], data, 0, settings, steps)
    assert training._resumable(partial, args)[0] == 0  # other arguments (save_freq): never resumed
    training.RESUME_EVERY, saved = every, training.RESUME_EVERY
    try:
        ckpt = training.train_method(methods_for(get_suite_env("reach-around"))["bc"], data, run_dir, 0, settings,
                                     steps)
    finally:
        training.RESUME_EVERY = saved
    info = json.loads((run_dir / "train_info.json").read_text())
    assert info["resumed_from_step"] == done and info["steps"] == steps and info["seconds"] > 0
    assert (ckpt / "model.safetensors").is_file() and not partial.exists()
    log = (run_dir / "train.log").read_text()
    assert "Resuming data order" in log and f"Checkpoint policy after step {done + every}" in log
    assert f"Checkpoint policy after step {steps}" in log


def test_the_camera_variant_has_its_own_frozen_choices(monkeypatch):
    """A choice validated on the camera variant applies there only, and the state variant's not to it."""
    from lerobot_pdp.benchmark import settings

    assert settings.budget_key(True, "images") == "quick+images" and settings.budget_key(False) == "full"
    monkeypatch.setitem(settings.FROZEN, ("reach-around", "quick+images"), {"vqbet": {"adapt": {"lr": 1e-3}}})
    assert settings.frozen_for("reach-around", True, "vqbet", obs="images") == {"adapt": {"lr": 1e-3}}
    assert settings.frozen_for("reach-around", True, "pdp", obs="images") == {}
    assert settings.frozen_for("reach-around", True, "vqbet") == {}
    assert settings.frozen_for("reach-around", True, "pdp")["sampler"] == [10, "trailing"]


def test_vqbet_outside_the_camera_variant_is_refused_with_the_reason(tmp_path):
    from lerobot_pdp.benchmark.protocol import run_benchmark
    from lerobot_pdp.benchmark.settings import BenchmarkConfig

    with pytest.raises(ValueError, match=r"unknown method\(s\) \['vqbet'\].*vqbet needs --obs images"):
        run_benchmark(BenchmarkConfig(env="reach-around", out=tmp_path / "b", methods=["vqbet"], seeds=[0]))
    assert not list((tmp_path / "b").glob("data/*"))  # refused before any dataset is made


def test_a_failing_checkpoint_hook_stops_the_training_it_follows(tmp_path):
    """run_logged stops the lerobot-train it reads when it is interrupted (Ctrl-C, or ``on_checkpoint`` failing):
    no training is left running unread, holding the cores and its output folder."""
    import os
    import sys

    from lerobot_pdp.benchmark.training import run_logged

    pid_file = tmp_path / "pid"
    child = (f"import os, pathlib, time; pathlib.Path({str(pid_file)!r}).write_text(str(os.getpid())); "
             "print('Checkpoint policy after step 10', flush=True); time.sleep(120)")

    def hook(step):
        raise RuntimeError(f"copying checkpoint {step} failed")

    with pytest.raises(RuntimeError, match="copying checkpoint 10 failed"):
        run_logged([sys.executable, "-c", child], tmp_path / "log", 20, "test", on_checkpoint=hook)
    with pytest.raises(ProcessLookupError):  # terminated and reaped
        os.kill(int(pid_file.read_text()), 0)


def test_the_training_progress_follows_lerobot_trains_rounded_step_counter():
    """lerobot-train logs ``step:<format_big_number(step)>`` every --log_freq steps: "2K" from 1500 on. The bar
    reads each log line as the next multiple of log_freq, so it neither stalls at 1000 nor jumps ahead."""
    from lerobot.utils.utils import format_big_number

    from lerobot_pdp.benchmark.training import logged_step

    done, seen = 0, []
    for step in range(80, 1601, 80):  # --steps=1600 --log_freq=80, as train_args sets them
        done = logged_step(f"INFO ... step:{format_big_number(step)} smpl:{format_big_number(step * 64)} loss:0.1",
                           done, 80)
        seen.append(done)
    assert seen == list(range(80, 1601, 80))
    assert logged_step("INFO Checkpoint policy after step 1000", 0, 80) is None
    resumed = logged_step("step:1K", 1000, 80)  # resumed from the step-1000 checkpoint: its first line, 1040
    assert resumed == 1040
