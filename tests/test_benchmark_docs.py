"""docs/benchmark.md's per-env ``lerobot-train`` commands are the benchmark's own: its env flags and budget."""

import re
import shlex
from pathlib import Path

import pytest

import lerobot_pdp.envs as envs
from lerobot_pdp.benchmark.settings import SETTINGS, methods_for
from lerobot_pdp.benchmark.training import train_args

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmark.md"


def _documented() -> dict[str, list[str]]:
    """The arguments of each ``lerobot-train`` line of the doc's training section, by the env its dataset names."""
    text = DOC.read_text().split("## Training PDP on the benchmark envs", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", text, re.S).group(1).replace("\\\n", " ")
    out = {}
    for line in block.splitlines():
        if line.startswith("lerobot-train"):
            args = shlex.split(line)[1:]
            root = next(a for a in args if a.startswith("--dataset.root="))
            out[root.split("data/", 1)[1]] = args
    return out


@pytest.mark.parametrize("env", list(SETTINGS))
def test_the_documented_training_command_is_the_benchmarks(env):
    documented = _documented()[env]
    settings = SETTINGS[env][0]  # the full budget
    pdp = train_args(methods_for(envs.get_suite_env(env))["pdp"], Path("data") / env, 0, settings, settings.steps)
    defaults = {"--policy.optimizer_lr=0.001", "--policy.embedding_lr=0.001", "--policy.scheduler_warmup_steps=100",
                "--policy.num_inference_steps=20", "--policy.timestep_spacing=leading",
                "--policy.use_clipped_model_output=false", "--policy.device=cpu"}  # PDPConfig's own defaults
    from lerobot_pdp import PDPConfig

    cfg = PDPConfig(device="cpu")
    assert (cfg.optimizer_lr, cfg.embedding_lr, cfg.scheduler_warmup_steps, cfg.num_inference_steps,
            cfg.timestep_spacing, cfg.use_clipped_model_output) == (1e-3, 1e-3, 100, 20, "leading", False)
    wanted = {a for a in pdp if a.startswith(("--policy.", "--steps=", "--batch_size=", "--num_workers="))} - defaults
    assert wanted <= set(documented), sorted(wanted - set(documented))
    assert {a for a in documented if a.startswith("--policy.")} <= {a for a in pdp if a.startswith("--policy.")}


def test_the_documented_ddim_steps_are_the_frozen_samplers():
    """The settings table's "DDIM steps (PDP, DP)" of each env's full budget: the sampler its validation froze
    (settings.FROZEN), else the budget's default."""
    from lerobot_pdp.benchmark.settings import frozen_for

    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
            for line in DOC.read_text().splitlines() if line.startswith("| ") and line.split("|")[1].strip() in SETTINGS}
    for env, row in rows.items():
        default = SETTINGS[env][0].inference_steps
        shown = []
        for method in ("pdp", "dp"):
            sampler = frozen_for(env, False, method, "state").get("sampler")
            shown.append(f"{sampler[0]} ({sampler[1]})" if sampler else str(default))
        assert row[4] == ", ".join(shown), (env, row[4], shown)
