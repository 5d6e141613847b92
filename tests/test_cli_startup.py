"""`lerobot-pdp` starts without importing torch or LeRobot for what needs neither: `--help`, a subcommand's help,
`steer` (typed beside a running robot: it must answer at once, not after LeRobot's policies import), and `search`'s
argument errors (named before seconds of imports). The policy's public names still register `--policy.type=pdp`
on first use."""

import json
import subprocess
import sys

import pytest
from policies import small_policy


@pytest.fixture(scope="module")
def small_checkpoint(synthetic_meta, tmp_path_factory):
    path = tmp_path_factory.mktemp("cli_startup") / "ckpt"
    small_policy(synthetic_meta).save_pretrained(path)
    return path

# Runs the CLI in a fresh interpreter and reports which heavy packages it imported.
PROBE = """
import contextlib, io, json, sys
from lerobot_pdp.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        rc = main(json.loads(sys.argv[1]))
    except SystemExit as e:  # argparse's --help
        rc = e.code
heavy = sorted({m.split(".")[0] for m in sys.modules} & {"torch", "lerobot", "diffusers", "gymnasium", "mujoco"})
print(json.dumps({"rc": rc, "heavy": heavy, "out": out.getvalue()}))
"""


def _cli(*argv: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE, json.dumps(list(argv))], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    return {**json.loads(proc.stdout.strip().splitlines()[-1]), "err": proc.stderr}


@pytest.mark.parametrize(("argv", "shown"), [(["--help"], "steer"), (["teach", "--help"], "(default 3000)"),
                                             (["make-dataset", "--help"], "reach-around")])
def test_help_imports_neither_torch_nor_lerobot(argv, shown):
    res = _cli(*argv)
    assert res["rc"] == 0 and res["heavy"] == [], res
    assert shown in res["out"], res["out"]  # the subcommands, teach's defaults, the suite's envs


def test_steer_writes_and_checks_without_torch_or_lerobot(tmp_path, small_checkpoint):
    steer = tmp_path / "steer.json"
    res = _cli("steer", str(steer), "--latent", "0.5", "-1.5e-05")
    assert res["rc"] == 0 and res["heavy"] == [], res
    assert json.loads(steer.read_text()) == {"latent": [0.5, -1.5e-05]}
    # checked against a checkpoint (its latent size and mode labels, read from config.json and the weights)
    res = _cli("steer", str(steer), "--latent", "1", "2", "3", "--policy-path", str(small_checkpoint))
    assert res["rc"] == 2 and res["heavy"] == [], res
    assert json.loads(steer.read_text()) == {"latent": [0.5, -1.5e-05]}  # a refused request writes nothing
    res = _cli("steer", str(steer), "--mode", "left-wide", "--policy-path", str(small_checkpoint))
    assert res["rc"] == 0 and res["heavy"] == [], res
    assert json.loads(steer.read_text()) == {"mode": "left-wide"}


@pytest.mark.parametrize(("extra", "said"), [(["--budget", "0"], "--budget must be >= 1, got 0"),
                                             (["--seed", "-1"], "argument --seed: must be an integer >= 0"),
                                             (["--waypoints", "scene", "--radius", "0"], "--radius must be a finite")])
def test_search_names_a_bad_argument_before_importing_torch(tmp_path, small_checkpoint, extra, said):
    res = _cli("search", str(small_checkpoint), "--env", "reach-around", *extra)
    assert res["rc"] == 2 and res["heavy"] == [] and said in res["err"], res
    res = _cli("search", str(tmp_path / "nope"), "--env", "reach-around")
    assert res["rc"] == 2 and res["heavy"] == [] and "no such checkpoint folder" in res["err"], res


def test_the_suite_envs_named_in_help_are_the_suite():
    import lerobot_pdp.envs as envs
    from lerobot_pdp.cli import SUITE_ENVS

    assert list(SUITE_ENVS) == sorted(envs.SUITE)


def test_import_lerobot_pdp_is_light_and_its_names_register_pdp():
    code = """
import sys, lerobot_pdp
light = "torch" not in sys.modules and "lerobot" not in sys.modules
from lerobot_pdp import PDPConfig, PDPPolicy, make_pdp_pre_post_processors
from lerobot.configs.policies import PreTrainedConfig
assert PreTrainedConfig.get_choice_class("pdp") is PDPConfig
assert "PDPPolicy" in dir(lerobot_pdp)
try:
    lerobot_pdp.nothing_here
except AttributeError as e:
    print(light, e)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "True module 'lerobot_pdp' has no attribute 'nothing_here'"
