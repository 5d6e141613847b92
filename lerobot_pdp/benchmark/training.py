"""Training one (method, seed) with LeRobot's own ``lerobot-train`` process, checkpoint reuse, and loading a
trained checkpoint with its processors the way ``lerobot-eval`` does."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .. import column_views
from ..atomic import write_text_atomic
from .machine import cpu_model
from .settings import VQBET_VQVAE_SHARE, Method, TrainSettings

# Two loader workers with one torch thread in the trainer overlap loading and the update on 2 cores.
# Measured when LeRobot's whole-row loading took ~3/4 of a step (before column_views; reach-around, PDP,
# B = 64): 0.10 s/step instead of 0.18 s/step (num_workers=0, 2 threads); workers with 2 trainer threads
# oversubscribed the cores and were slower than no workers at all.
TRAIN_NUM_WORKERS = int(os.environ.get("LEROBOT_PDP_TRAIN_WORKERS", "2"))


# Camera policies are compute-bound instead (a ResNet pass per image; ~1.5 s/step at B = 64 on one thread,
# 64x64 images, the loaders idle most of the time): LEROBOT_PDP_TRAIN_THREADS sets the trainer's threads.
_THREADS = os.environ.get("LEROBOT_PDP_TRAIN_THREADS", "1" if TRAIN_NUM_WORKERS > 0 else "")
TRAIN_THREADS_ENV = {"OMP_NUM_THREADS": _THREADS, "MKL_NUM_THREADS": _THREADS} if _THREADS else {}

# lerobot-train saves a checkpoint this often (and at the end), so that a run cut short (a machine going away,
# a job's time limit) goes on from its last checkpoint with lerobot-train's own resume (sample-exact in
# LeRobot 0.6: optimizer, scheduler, RNG and data order) instead of starting over. A PDP or DP checkpoint
# with its optimizer state is ~20 MB; older ones are deleted as training goes.
RESUME_EVERY = 1000


_LOGGED_STEP = re.compile(r"step:(\d+)(K?)")


def logged_step(line: str, done: int, log_freq: int) -> int | None:
    """The training step a ``lerobot-train`` log line reports (None: not a step line), given the last one
    ``done``. Its counter is rounded from 1000 on ("step:2K" at 1500), but a line comes every ``--log_freq``
    steps: the next multiple of ``log_freq`` after ``done`` is exact where the rounded counter is not."""
    m = _LOGGED_STEP.search(line)
    if m is None:
        return None
    if not m.group(2):
        return int(m.group(1))
    return (done // log_freq + 1) * log_freq if log_freq > 0 else int(m.group(1)) * 1000


def run_logged(args: list[str], log: Path, total_steps: int, desc: str, start: int = 0,
                on_checkpoint=None) -> None:
    """Run ``lerobot-train`` with its output in ``log`` (appended to when resuming from step ``start``); a
    progress bar follows its logged step counter; ``on_checkpoint(step)`` runs as each checkpoint starts."""
    from tqdm.auto import tqdm

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TQDM_DISABLE": "1", **TRAIN_THREADS_ENV, **column_views.child_env()}
    log_freq = next((int(a.partition("=")[2]) for a in args if a.startswith("--log_freq=")), 0)
    saving = re.compile(r"Checkpoint policy after step (\d+)")
    # line-buffered: a run killed from outside keeps its log up to the kill
    with open(log, "a" if start else "w", buffering=1) as fh, tqdm(total=total_steps, initial=start, desc=desc, unit="step") as bar:
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        assert proc.stdout is not None
        done = start
        try:
            for line in proc.stdout:
                fh.write(line)
                step = logged_step(line, done, log_freq)
                if step is not None:
                    step = min(step, total_steps)
                    bar.update(max(0, step - done))
                    done = max(done, step)
                m = saving.search(line)
                if m and on_checkpoint is not None:
                    on_checkpoint(int(m.group(1)))
        except BaseException:  # Ctrl-C, or on_checkpoint failed: no training left running without its reader
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            raise
        rc = proc.wait()
        if rc == 0:
            bar.update(total_steps - done)
    if rc != 0:
        tail = "".join(log.read_text().splitlines(keepends=True)[-40:])
        raise RuntimeError(f"{args[0]} failed with exit code {rc}; see {log}\n{tail}")


def train_args(method: Method, dataset: Path, seed: int, settings: TrainSettings, steps: int,
               device: str = "cpu") -> list[str]:
    """The ``lerobot-train`` command line of one (method, seed) run, without ``--output_dir``."""
    exe = Path(sys.executable).parent / "lerobot-train"
    lr_args = [f"--policy.optimizer_lr={settings.lr}"]
    if method.policy_type == "pdp":
        lr_args.append(f"--policy.embedding_lr={settings.lr}")
    schedule = (
        [f"--policy.scheduler_warmup_steps={min(settings.warmup_steps, steps // 10)}"]
        if method.policy_type in ("pdp", "diffusion", "vqbet") else []
    )
    if method.policy_type == "vqbet":  # its VQ-VAE phase is part of the same step budget
        schedule.append(f"--policy.n_vqvae_training_steps={max(1, round(steps * VQBET_VQVAE_SHARE))}")
    args = [
        str(exe) if exe.exists() else "lerobot-train",
        f"--policy.type={method.policy_type}", "--policy.push_to_hub=false", f"--policy.device={device}",
        f"--dataset.repo_id=local/{dataset.name}", f"--dataset.root={dataset}",
        f"--steps={steps}", f"--batch_size={settings.batch_size}", f"--seed={seed}",
        f"--save_freq={min(steps, RESUME_EVERY)}", f"--log_freq={max(steps // 20, 1)}", f"--num_workers={TRAIN_NUM_WORKERS}",
        "--wandb.enable=false",
        # the shared budget comes last so that it wins over any per-method default (same lr for everyone)
        *method.overrides, *lr_args, *schedule,
    ]
    if settings.drop_n_last_frames is not None:
        args.append(f"--policy.drop_n_last_frames={settings.drop_n_last_frames}")
    if method.policy_type in ("pdp", "diffusion"):
        args.append(f"--policy.num_inference_steps={settings.inference_steps}")
    if method.policy_type == "pdp":  # DP's LeRobot config has no such fields: load_policy sets its scheduler
        args += pdp_sampler_args(settings.timestep_spacing)
    # a flag given twice (a method's default, then the shared budget) once, with the value lerobot-train would take
    # (its last): the command recorded in train_info.json reads as it acts
    last = {a.partition("=")[0]: i for i, a in enumerate(args) if a.startswith("--")}
    return [a for i, a in enumerate(args) if not a.startswith("--") or last[a.partition("=")[0]] == i]


def pdp_sampler_args(spacing: str) -> list[str]:
    """PDP flags for the benchmark's shared sampler: diffusers' DDIM on ``spacing``'s grid, stepped as
    LeRobot's ``diffusion`` steps (no clipped-noise re-derivation), so both methods sample identically;
    "even" keeps PDP's own grid and rule (checkpoints trained before the shared sampler)."""
    if spacing == "even":
        return ["--policy.timestep_spacing=even", "--policy.use_clipped_model_output=true"]
    return [f"--policy.timestep_spacing={spacing}", "--policy.use_clipped_model_output=false"]


def train_method(method: Method, dataset: Path, run_dir: Path, seed: int, settings: TrainSettings,
                 steps: int, device: str = "cpu") -> Path:
    """Train with LeRobot's own ``lerobot-train``; the checkpoint lands in ``run_dir/pretrained_model``.

    Training runs in ``run_dir/.train-partial`` and is moved into place when it ends. A run interrupted
    after its first checkpoint resumes from the last one when called again with the same arguments; a
    partial run with other arguments is discarded."""
    ckpt = run_dir / "pretrained_model"
    args = train_args(method, dataset, seed, settings, steps, device)
    if (ckpt / "model.safetensors").is_file():
        _check_reusable(run_dir, args)
        print(f"[benchmark] {method.name} seed {seed}: trained already ({ckpt}), reused")
        return ckpt
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("eval.json", "traces.json", "init_ablation.json", "sweep.json", "train_info.json"):  # earlier model
        (run_dir / stale).unlink(missing_ok=True)
    shutil.rmtree(run_dir / "validation", ignore_errors=True)
    for old in run_dir.glob(".train-*"):  # temporary folders of runs killed before resuming existed
        if old.name != _PARTIAL:
            shutil.rmtree(old, ignore_errors=True)
    partial = run_dir / _PARTIAL
    tmp_out = partial / "out"
    start, seconds_before = _resumable(partial, args)
    if start == 0:
        left = _last_step(tmp_out)
        if left is not None:  # a partial run of another command: say what is thrown away
            print(f"[benchmark] {run_dir}: discarding a partial training (checkpoint at step {left}) made with "
                  "other lerobot-train arguments; training from the start")
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir()
        write_text_atomic(partial / "progress.json", json.dumps({"args": args, "seconds": {}}))
        run_args = [*args, f"--output_dir={tmp_out}"]
    else:  # lerobot-train's own resume: the checkpoint's train_config.json holds every other argument
        config = tmp_out / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        run_args = [args[0], f"--config_path={config}", "--resume=true", f"--output_dir={tmp_out}"]
    log = run_dir / "train.log"
    t0 = time.time()

    def on_checkpoint(step: int) -> None:
        """Record the training time up to ``step`` and delete checkpoints older than the last complete one
        (the one ``step`` starts writing now is not complete yet)."""
        progress = json.loads((partial / "progress.json").read_text())
        progress["seconds"][str(step)] = seconds_before + time.time() - t0
        write_text_atomic(partial / "progress.json", json.dumps(progress))
        last = _last_step(tmp_out)
        for d in (tmp_out / "checkpoints").glob("[0-9]*"):
            if last is not None and int(d.name) < last:
                shutil.rmtree(d, ignore_errors=True)

    try:
        run_logged(run_args, log, steps, f"train {method.name} seed {seed}", start, on_checkpoint)
        src = tmp_out / "checkpoints" / "last" / "pretrained_model"
        if not (src / "model.safetensors").is_file():
            raise RuntimeError(f"lerobot-train finished but wrote no checkpoint at {src}; see {log}")
        info = {"seconds": seconds_before + time.time() - t0, "steps": steps, "args": _portable(args, run_dir),
                "column_views": column_views.active(),  # LeRobot's loader sped up: the seconds depend on it
                "cpu": cpu_model()}  # the seconds and the trained weights' low-order bits depend on it too
        if start:
            info["resumed_from_step"] = start
        # train_info.json first: a checkpoint must never be found without the arguments it was trained with
        # (that would pass as one copied in by hand and be reused unchecked).
        write_text_atomic(run_dir / "train_info.json", json.dumps(info, indent=1))
        os.replace(src, ckpt)
        shutil.rmtree(partial, ignore_errors=True)
    finally:  # a failed run leaves its log and, once it has a checkpoint, what it can resume from
        if _last_step(tmp_out) is None:
            shutil.rmtree(partial, ignore_errors=True)
    return ckpt


_PARTIAL = ".train-partial"


def _last_step(out: Path) -> int | None:
    """Step of the last complete checkpoint under a lerobot-train output folder (None if there is none):
    lerobot-train points ``checkpoints/last`` at a checkpoint once it is fully written."""
    step_file = out / "checkpoints" / "last" / "training_state" / "training_step.json"
    try:
        return int(json.loads(step_file.read_text())["step"])
    except (OSError, ValueError, KeyError):
        return None


def _resume_key(args: list[str]) -> list[str]:
    return [a for a in args if a.partition("=")[0] not in ("--num_workers", "--log_freq")]


def _resumable(partial: Path, args: list[str]) -> tuple[int, float]:
    """(step, training seconds up to it) of a partial run that can go on with ``args``; (0, 0) if none."""
    step = _last_step(partial / "out")
    try:
        progress = json.loads((partial / "progress.json").read_text())
    except (OSError, ValueError):
        return 0, 0.0
    # the same command but for loader workers and logging: a resumed run keeps the checkpoint's configuration
    # (the sampler and device included), so those must not differ
    if step is None or _resume_key(progress.get("args", [])) != _resume_key(args):
        return 0, 0.0
    return step, float(progress["seconds"].get(str(step), 0.0))


def _portable(args: list[str], run_dir: Path) -> list[str]:
    """The command as recorded in ``train_info.json``: the dataset relative to the run folder, no temporary
    output folder, the bare program name, so that a results folder can be moved or committed."""
    out = ["lerobot-train"]
    for a in args[1:]:
        key, _, value = a.partition("=")
        if key == "--output_dir":
            continue
        out.append(f"{key}={os.path.relpath(value, run_dir)}" if key == "--dataset.root" else a)
    return out


# Flags that do not change what a run learns: where it writes and how often it logs and saves, how many
# loader processes feed it, the device it runs on, and the DDIM sampler it acts with (evaluations record
# their own sampler and are redone when it changes).
_NOT_TRAINING = ("--output_dir", "--dataset.root", "--log_freq", "--save_freq", "--num_workers",
                 "--policy.num_inference_steps", "--policy.timestep_spacing", "--policy.use_clipped_model_output",
                 "--policy.device")


def _flags(args: list[str]) -> dict[str, str]:
    pairs = (a.partition("=") for a in args[1:] if a.startswith("--"))
    return {k: v for k, _, v in pairs if k not in _NOT_TRAINING}


def _check_reusable(run_dir: Path, args: list[str]) -> None:
    """Refuse to reuse a checkpoint trained with other arguments (steps, lr, method flags): resuming into an
    old ``--out`` after the protocol changed would otherwise put stale runs into the new table. Checkpoints
    without a ``train_info.json`` (copied in by hand) are reused as they are."""
    info = run_dir / "train_info.json"
    recorded = json.loads(info.read_text()).get("args") if info.is_file() else None
    if recorded is None:
        return
    old, new = _flags(recorded), _flags(args)
    diff = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if diff:
        shown = "; ".join(f"{k}: trained with {old.get(k, '(absent)')}, now {new.get(k, '(absent)')}" for k in diff)
        raise ValueError(f"{run_dir} was trained with other lerobot-train arguments ({shown}); use another --out "
                         f"or delete {run_dir} to retrain")


def load_policy(ckpt: Path, inference_steps: int | None = None, device: str = "cpu",
                timestep_spacing: str | None = None):
    """Policy + its saved pre/post processors on ``device``, as lerobot-eval loads them.

    ``inference_steps`` replaces the checkpoint's ``num_inference_steps`` and ``timestep_spacing`` its DDIM
    grid (diffusion policies only): "leading" / "trailing" give PDP and DP the same sampler, diffusers' DDIM
    as LeRobot's ``diffusion`` steps it (DP's scheduler is rebuilt from its own config with that spacing);
    "even" is PDP's own grid and step rule, which DP does not have.
    """
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    import lerobot_pdp.baselines  # noqa: F401  (registers mlp_bc in any process, spawned workers included)
    import lerobot_pdp.configuration_pdp  # noqa: F401  (and pdp: `import lerobot_pdp` alone does not)

    cfg = PreTrainedConfig.from_pretrained(ckpt)
    cfg.device = device
    if inference_steps is not None and hasattr(cfg, "num_inference_steps"):
        if not 1 <= inference_steps <= cfg.num_train_timesteps:
            raise ValueError(f"inference_steps={inference_steps} for {ckpt}: expected 1..{cfg.num_train_timesteps} "
                             "(the checkpoint's num_train_timesteps)")
        cfg.num_inference_steps = int(inference_steps)
    if timestep_spacing is not None and cfg.type == "pdp":
        for flag in pdp_sampler_args(timestep_spacing):
            key, _, value = flag.removeprefix("--policy.").partition("=")
            setattr(cfg, key, value == "true" if value in ("true", "false") else value)
    policy = get_policy_class(cfg.type).from_pretrained(ckpt, config=cfg)
    policy.eval()
    if timestep_spacing is not None and cfg.type == "diffusion":
        if timestep_spacing == "even":
            raise ValueError("timestep_spacing='even' is PDP's own sampler; LeRobot's diffusion samples on "
                             "diffusers' grids: use 'leading' or 'trailing'")
        from diffusers import DDIMScheduler

        sched = policy.diffusion.noise_scheduler
        policy.diffusion.noise_scheduler = DDIMScheduler.from_config(sched.config, timestep_spacing=timestep_spacing)
    # the saved device step holds the training device: point it at this one (lerobot-eval does the same)
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(ckpt),
                                         preprocessor_overrides={"device_processor": {"device": device}})
    return policy, pre, post


def load_run(run_dir: Path):
    """A benchmark run's policy + processors sampling as its ``eval.json`` was made (same DDIM steps and
    grid; the checkpoint's own when there is no evaluation yet). Diagnostics use it to replay the
    benchmark's rollouts."""
    run_dir = Path(run_dir)
    ev = run_dir / "eval.json"
    made = json.loads(ev.read_text()) if ev.is_file() else {}
    return load_policy(run_dir / "pretrained_model", made.get("inference_steps"), timestep_spacing=made.get("timestep_spacing"))
