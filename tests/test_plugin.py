"""The policy plugin imports the policy only; LeRobot discovers it (and the lab's own plugins: simulators,
sim robot, teleoperator, baselines) by distribution name, also from a regular (non-editable) install."""

import json
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CHECK = """
import lerobot_pdp, sys
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()
assert "lerobot_policy_pdp" in sys.modules, "plugin module not imported by discovery"
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class
from lerobot.envs.configs import EnvConfig
cfg_cls = PreTrainedConfig.get_choice_class("pdp")
pol_cls = get_policy_class("pdp")
env_cls = EnvConfig.get_choice_class("pdp_reach_around")
print(lerobot_pdp.__file__, cfg_cls.__name__, pol_cls.__name__, env_cls.__name__)
"""

# What importing the policy plugin loads: none of the lab, and no change to LeRobot's dataset reader.
LEAN = """
import json, sys
import lerobot_policy_pdp
from lerobot.datasets.dataset_reader import DatasetReader
lab = sorted(m for m in sys.modules if m.split(".")[0] in ("mujoco", "gymnasium_robotics", "matplotlib")
             or m.startswith(("lerobot_pdp.envs", "lerobot_pdp.robots", "lerobot_pdp.teleoperators",
                              "lerobot_pdp.baselines", "lerobot_pdp.benchmark")))
print(json.dumps({"lab": lab, "patched": bool(getattr(DatasetReader.__init__, "_pdp_column_views", False))}))
"""

# LeRobot's own discovery registers the lab from its distributions.
DISCOVERY = """
import json, sys
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig
print(json.dumps([PreTrainedConfig.get_choice_class("pdp").__name__, PreTrainedConfig.get_choice_class("mlp_bc").__name__,
                  EnvConfig.get_choice_class("pdp_reach_around").__name__, RobotConfig.get_choice_class("pdp_sim").__name__,
                  TeleoperatorConfig.get_choice_class("pdp_waypoints").__name__]))
"""


def _python(code: str, **env: str) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k != "LEROBOT_PDP_COLUMN_VIEWS"} | env
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, timeout=300)


def test_the_policy_plugin_imports_the_policy_and_nothing_else():
    out = _python(LEAN)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.splitlines()[-1]) == {"lab": [], "patched": False}
    asked = _python(LEAN, LEROBOT_PDP_COLUMN_VIEWS="1")  # the benchmark's trainings ask for the column views
    assert asked.returncode == 0, asked.stderr[-3000:]
    import lerobot

    from lerobot_pdp import column_views

    assert json.loads(asked.stdout.splitlines()[-1])["patched"] is column_views.affected(lerobot.__version__)


def test_lerobot_discovers_the_lab_plugins_by_distribution_name():
    out = _python(DISCOVERY)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.splitlines()[-1]) == ["PDPConfig", "MLPBCConfig", "PDPReachAroundEnvConfig",
                                                       "PDPSimConfig", "PDPWaypointsConfig"]


@pytest.mark.slow
def test_register_third_party_plugins_finds_pdp_from_wheel(tmp_path):
    wheel_dir = tmp_path / "wheels"
    src = tmp_path / "src"
    # build from a copy so the checkout gets no build/ or egg-info
    files = subprocess.run(["git", "-C", str(ROOT), "ls-files"], check=True, capture_output=True, text=True).stdout.split()
    for f in files:
        if (ROOT / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            (src / f).write_bytes((ROOT / f).read_bytes())
    projects = [src, *sorted(p for p in (src / "plugins").iterdir() if (p / "pyproject.toml").is_file())]
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheel_dir),
                    *map(str, projects)], check=True, capture_output=True)
    wheels = sorted(wheel_dir.glob("*.whl"))
    assert len(wheels) == len(projects) == 5, wheels  # the policy and the lab's four plugins
    # a fresh venv that sees the project's dependencies but not its editable install
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    site = next((venv / "lib").glob("python3*/site-packages"))
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), *map(str, wheels)],
                   check=True, capture_output=True)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([str(venv / "bin" / "python"), "-c", CHECK], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    path, cfg_name, pol_name, env_name = out.stdout.split()[-4:]
    assert str(site) in path, f"imported {path}, not the wheel install"
    assert (cfg_name, pol_name, env_name) == ("PDPConfig", "PDPPolicy", "PDPReachAroundEnvConfig")
