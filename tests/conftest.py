"""Shared fixtures: offline Hugging Face, a real synthetic LeRobotDataset v3, a PDP trained on reach-around by
lerobot-train."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Forced, not defaulted: tests never download (whatever the caller's environment says) and never read a
# soft-DTW cache they did not write themselves (pytest-xdist's workers share their controller's).
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["HF_DATASETS_OFFLINE"] = "1"
if not os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["LEROBOT_PDP_CACHE"] = tempfile.mkdtemp(prefix="pdp-cache-")
os.environ.setdefault("TQDM_DISABLE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs two pytest workers on the two cores: one torch thread each (and in their subprocesses),
    # or two workers' spinning OpenMP threads oversubscribe the cores (docs/performance.md, "Threads").
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    if "torch" in sys.modules:  # already imported (by a plugin): set its pool too
        sys.modules["torch"].set_num_threads(1)
else:
    # One process: the thread count a PDP build would set (half the cores) from the start, so that it does not
    # depend on whether an earlier test happened to build one.
    from lerobot_pdp.cpu_threads import apply_cpu_threads

    apply_cpu_threads(None)

import pytest  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))

# LeRobot's AV1 video encoder raises the encoding thread to real-time priority where it may (as root) and leaves it
# there (lerobot_pdp/cpu_priority.py). A test that writes a video dataset in this process would otherwise run every
# later test here, and every process they start (lerobot-train, lerobot-eval), at that priority: on two cores they
# starve the other worker (seen in a full run: a worker at SCHED_FIFO 99). Each test phase ends at the priority
# the session started with; make-dataset and pdp_sim's record loop undo it themselves (tested there).
from lerobot_pdp import cpu_priority  # noqa: E402

_SCHEDULING = cpu_priority.current()


def pytest_runtest_makereport(item, call):
    """Called after each phase of a test (setup, call, teardown): the next phase starts at the session's priority."""
    cpu_priority.restore(_SCHEDULING)


VENV_BIN = Path(sys.executable).parent


def lerobot_cli(name: str) -> str:
    """Path of a LeRobot console script in this interpreter's environment."""
    p = VENV_BIN / name
    return str(p) if p.exists() else name


def _descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (Linux /proc; elsewhere none)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


def run_cli(args: list[str], timeout: float = 900, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a console script as a real subprocess; on failure show its output tail."""
    from lerobot_pdp import column_views

    # the benchmark's trainings read datasets through column views (a child asks for them by its environment)
    full_env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", **column_views.child_env(), **(env or {})}
    cpu_priority.restore(_SCHEDULING)  # the process inherits this one's priority: never a video encoder's real-time one
    # On a timeout the whole tree goes (accelerate's ranks, which torchrun starts in sessions of their own), not
    # only the launcher. SIGABRT first: with PYTHONFAULTHANDLER each Python process prints every thread's stack,
    # so the error shows where it hung; then SIGKILL for what is left.
    full_env["PYTHONFAULTHANDLER"] = "1"
    with subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=full_env) as popen:
        try:
            out, err = popen.communicate(timeout=timeout)
        except BaseException as exc:
            out, err = "", ""
            tree = [popen.pid, *_descendants(popen.pid)]  # before a signal: orphans are reparented
            for sig, wait in ((signal.SIGABRT, 10), (signal.SIGKILL, 60)):
                for pid in reversed(tree) if sig == signal.SIGABRT else tree:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, sig)
                    if sig == signal.SIGABRT:  # one stack at a time: dumped together they interleave in the pipe
                        time.sleep(0.3)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    out, err = popen.communicate(timeout=wait)
                    break
            if isinstance(exc, subprocess.TimeoutExpired):
                raise AssertionError(f"{' '.join(args)} still ran after {timeout} s (it and its children were killed; "
                                     f"stacks at the kill below):\n{out[-3000:]}\n{err[-12000:]}") from None
            raise
    proc = subprocess.CompletedProcess(args, popen.returncode, out, err)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")
    return proc


def train_tiny_pdp(dataset: Path, out: Path, *extra: str, steps: int = 4, batch_size: int = 8) -> Path:
    """A real ``lerobot-train`` of a small PDP on ``dataset`` for ``steps`` steps (``extra``: more flags);
    returns the last checkpoint's ``pretrained_model`` folder."""
    run_cli([lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.push_to_hub=false", "--policy.device=cpu",
             "--policy.down_dims=[16,32]", "--dataset.repo_id=local/tiny", f"--dataset.root={dataset}",
             f"--steps={steps}", f"--batch_size={batch_size}", "--num_workers=0", f"--save_freq={steps}",
             "--log_freq=1", "--wandb.enable=false", f"--output_dir={out}", *extra], timeout=600)
    return out / "checkpoints" / "last" / "pretrained_model"


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny models, small batches: one intra-op thread for a module. With 2 threads on a 2-core machine that has
    any other load, OpenMP barriers made the DP adaptation test ~170x slower here (229 s instead of 1.4 s)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory) -> Path:
    """4-mode 2-D dataset, 10 episodes per mode (a real LeRobotDataset v3 on disk)."""
    from synthetic import write_dataset

    root = tmp_path_factory.mktemp("data") / "synthetic"
    return write_dataset(root, episodes_per_mode=10, seed=0)


@pytest.fixture(scope="session")
def synthetic_meta(synthetic_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    return LeRobotDatasetMetadata("local/synthetic", root=synthetic_dataset)


@pytest.fixture(scope="session")
def reach_around_pdp(tmp_path_factory) -> Path:
    """Checkpoint of PDP trained on reach-around (10 demos per mode, real MuJoCo) by a real `lerobot-train`
    process, the protocol's way (2 loader workers). Shared by the steering tests: the suite's most expensive
    fixture (503 s on 2 idle cores, 2026-11-24). 3000 steps: at 1500, scene-3 success after fitting was
    75-90 % depending on the fitting seed; the full 6000-step setting reaches 100 % (docs/results.md)."""
    from lerobot_pdp.benchmark.settings import TrainSettings, methods_for
    from lerobot_pdp.benchmark.training import train_method
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.envs.recording import make_dataset

    root = tmp_path_factory.mktemp("reach_around")
    data = make_dataset("reach-around", root / "data", scene=0, episodes_per_mode=10, seed=0, progress=False)
    return train_method(methods_for(get_suite_env("reach-around"))["pdp"], data, root / "run", 0,
                        TrainSettings(steps=3000), 3000)
