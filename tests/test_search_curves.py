"""``lerobot-pdp search-curves``: every method and budget point recorded, best-so-far by the search's own score,
DP's per-env noises, a finished record reused, bad input named.

The runs are small and untrained (PDP with random FiLM layers, so that latents act differently; DP with random
weights), on reach-around with episodes cut to 30 steps: the machinery, not the numbers (those need trained
checkpoints, docs/benchmark.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_pdp.benchmark import search_curves as sc
from lerobot_pdp.cli import main as cli
from lerobot_pdp.latent_search import Candidate, SearchResult

SEED = 100


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """A benchmark output folder holding a small PDP and a small DP run of seed 100, saved as lerobot-train saves
    them (weights + processors)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_pdp import PDPConfig
    from lerobot_pdp.benchmark.baselines import dp_config_kwargs
    from lerobot_pdp.denoiser import LatentFiLM
    from lerobot_pdp.envs.recording import make_dataset

    out = tmp_path_factory.mktemp("curves") / "bench"
    data = make_dataset("reach-around", out / "data" / "reach_around_scene0", scene=0, episodes_per_mode=1,
                        progress=False)
    meta = LeRobotDatasetMetadata("local/ra", root=data)
    torch.manual_seed(0)
    pdp_cfg = PDPConfig(device="cpu", push_to_hub=False, down_dims=(16, 32), trace_dims=[0, 1, 2],
                        num_inference_steps=4, fit_steps=2)
    dp_cfg = DiffusionConfig(device="cpu", push_to_hub=False,
                             **dp_config_kwargs({"down_dims": (16, 32), "num_inference_steps": 4}))
    for name, cfg in (("pdp", pdp_cfg), ("dp", dp_cfg)):
        policy = make_policy(cfg, ds_meta=meta)
        for m in policy.modules():
            if isinstance(m, LatentFiLM):
                torch.nn.init.normal_(m.mlp[-1].weight, std=2.0)
        ckpt = out / "runs" / name / f"seed{SEED}" / "pretrained_model"
        policy.save_pretrained(ckpt)
        for proc in make_pre_post_processors(cfg, dataset_stats=meta.stats):
            proc.save_pretrained(ckpt)
    return out


def measure(results: Path, dest: Path, scene: str = "val1", **kw):
    kw = {"confirm_rollouts": 0, **kw}  # one search read at every budget (confirmation: its own test below)
    return sc.run_search_curves(results, "reach-around", scene, SEED, dest, budgets=[8, 4], rollouts=2,
                                rollouts_per_candidate=2, max_episode_steps=30, progress=False, **kw)


def test_best_so_far_is_the_first_best_within_each_budget():
    scores = [0.0, 0.5, 0.5, 0.2, 1.0]
    res = SearchResult(None, 0.0, 0.0, [Candidate(torch.zeros(2), s, s, 2, 0) for s in scores], "cma", 0, 10, 2, "success",
                       best_trace=[(2, 0), (4, 1), (10, 4)])  # as the search records it: strictly better only
    assert sc.best_so_far(res, [2, 4, 6, 9, 100]) == [(2, 2, 0), (4, 4, 1), (6, 6, 1), (9, 8, 1), (100, 10, 4)]


def test_curves_record_every_method_and_budget_and_a_rerun_reuses_them(results, tmp_path, monkeypatch):
    dest = tmp_path / "curves"
    book = measure(results, dest)
    recs = book["records"]
    assert sorted(recs) == sorted(f"reach-around/val1/seed{SEED}/success/{m}" for m in sc.METHODS)
    for method, rec in ((r["method"], r) for r in recs.values()):
        pts = rec["points"]
        assert [p["budget"] for p in pts] == ([0] if method == "fit" else [4, 8])
        assert all(p["n"] == 2 and 0 <= p["success"] <= 1 and 0 <= p["collision"] <= 1 for p in pts)
        if method == "fit":
            continue
        assert [p["rollouts_used"] for p in pts] == [4, 8] and rec["search"]["rollouts_used"] == 8
        # the best so far never gets worse by the search's own score, and its time only grows
        assert pts[0]["search_score"] <= pts[1]["search_score"] and 0 < pts[0]["seconds"] <= pts[1]["seconds"]
        assert pts[0]["candidate"] < 2 <= rec["search"]["candidates"] == 4
        assert pts[0]["norm"] == pytest.approx(float(np.linalg.norm(pts[0]["noise" if method == "dp_noise" else "latent"])))
    # z_fit starts from the fit; DP's noise from zero with CMA-ES's population rule in horizon x action_dim numbers
    assert recs[f"reach-around/val1/seed{SEED}/success/z_fit"]["fit"]["z"] == recs[
        f"reach-around/val1/seed{SEED}/success/fit"]["points"][0]["latent"]
    dp = recs[f"reach-around/val1/seed{SEED}/success/dp_noise"]
    assert np.asarray(dp["points"][0]["noise"]).shape == (16, 3) and dp["search"]["popsize"] == 4 + int(3 * np.log(48))
    s = dp["settings"]
    assert s["evaluation_seeds"] == [SEED * 10_000 + 101, SEED * 10_000 + 102]
    assert s["search_seeds"] == [SEED * 10_000 + 5_101, SEED * 10_000 + 5_102] and "adapt" not in s
    table = (dest / sc.TABLE).read_text()
    assert "## reach-around val1, seed 100, scored by success" in table and "| dp_noise |" in table
    assert sc._scene_name(3) == "scene 3" and sc._scene_name("val1") == "val1"
    assert (dest / sc.FIGURE).stat().st_size > 10_000

    # a rerun with the same settings reuses every record: nothing is searched or rolled out again
    def refuse(*a, **kw):
        raise AssertionError("rolled out again")

    for name in ("search_latent", "search_dp_noise", "run_rollouts"):
        monkeypatch.setattr(sc, name, refuse)
    assert measure(results, dest)["records"] == json.loads(json.dumps(recs))
    # other settings (more evaluation rollouts) are measured anew
    with pytest.raises(AssertionError, match="rolled out again"):
        sc.run_search_curves(results, "reach-around", "val1", SEED, dest, budgets=[4, 8], rollouts=3,
                             max_episode_steps=30, methods=["z_modes"], confirm_rollouts=0, progress=False)


def test_waypoint_curves_search_without_a_demonstration(results, tmp_path):
    book = measure(results, tmp_path / "wp", scene="val3", score="waypoints", radius=0.08)
    recs = book["records"]
    assert sorted(r["method"] for r in recs.values()) == ["dp_noise", "z_modes"]
    for rec in recs.values():
        assert rec["score"] == "waypoints" and rec["settings"]["objective"]["radius"] == 0.08
        assert len(rec["settings"]["objective"]["waypoints"]) == 4 and "adapt" not in rec["settings"]
        assert all(0 <= p["waypoint_score"] <= 1 for p in rec["points"])
    assert not (results / "data" / "reach_around_scene_val3_demo").exists()  # no demonstration made


def test_waypoints_then_success_is_a_score_of_its_own(results, tmp_path):
    """--score waypoints_finish: its own records beside the way-point ones, the objective saying so."""
    dest = tmp_path / "wp"
    measure(results, dest, scene="val3", score="waypoints", radius=0.08, methods=["z_modes"])
    book = measure(results, dest, scene="val3", score="waypoints_finish", radius=0.08, methods=["z_modes"])
    recs = {r["score"]: r for r in book["records"].values()}
    assert sorted(recs) == ["waypoints", "waypoints_finish"]
    assert recs["waypoints_finish"]["settings"]["objective"]["finish"] is True
    assert "finish" not in recs["waypoints"]["settings"]["objective"]
    for p in recs["waypoints_finish"]["points"]:  # the search's score may pass 1, the reported progress may not
        assert 0 <= p["waypoint_score"] <= 1 and 0 <= p["search_score"] <= 2
    assert "scored by waypoints_finish" in (dest / sc.TABLE).read_text()


def test_confirmed_curves_run_one_search_per_budget(results, tmp_path):
    """With confirmation a budget's best is what a search of that budget returns: one search per budget, every
    point's best confirmed on its extra seeds, the setting and the seeds it used in the record."""
    book = sc.run_search_curves(results, "reach-around", "val1", SEED, tmp_path / "c", budgets=[20, 24], rollouts=2,
                                rollouts_per_candidate=2, confirm_rollouts=4, max_episode_steps=30,
                                methods=["z_modes", "dp_noise"], progress=False)
    for rec in book["records"].values():
        assert rec["settings"]["confirm_rollouts"] == 4
        assert rec["settings"]["search_seeds"] == [SEED * 10_000 + 5_101, SEED * 10_000 + 5_104]
        # z_modes: the 8 mode means (16 rollouts), the best confirmed (2 more), then what the budget still pays
        assert [p["budget"] for p in rec["points"]] == [20, 24] and rec["search"]["rollouts_used"] <= 24
        assert all(p["search_rollouts"] == 4 and p["rollouts_used"] <= p["budget"] for p in rec["points"])
        search = rec["search"]  # the largest budget's search, and what all the budgets' searches took
        assert search["budget"] == 24
        assert search["seconds_all_budgets"] >= search["seconds"]
    with pytest.raises(ValueError, match=r"confirm_rollouts must be 0 \(off\) or an integer in 3..4000"):
        sc.run_search_curves(results, "reach-around", "val1", SEED, tmp_path / "c", budgets=[8], confirm_rollouts=2)


def test_per_env_noises_act_per_env(results):
    """Two envs under different noises act differently; under equal noises, identically."""
    import gymnasium as gym

    from lerobot_pdp.benchmark.baselines import PerEnvNoisePolicy
    from lerobot_pdp.benchmark.training import load_policy
    from lerobot_pdp.envs import get_suite_env

    policy, pre, post = load_policy(results / "runs" / "dp" / f"seed{SEED}" / "pretrained_model")
    suite = get_suite_env("reach-around")

    def factory():
        return gym.make(suite.gym_id, scene=0, max_episode_steps=12, disable_env_checker=True)

    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(16, 3, generator=g), torch.randn(16, 3, generator=g)
    with sc.NoiseCandidateRollouts(policy, factory, 1, 7, (pre, post)) as run:
        differ, same = run([a, b]), run([a, a])
    # Equal up to float32 rounding: a row's kernel path (and so its last bits) may depend on its batch position.
    np.testing.assert_allclose(same[0][0].states, same[1][0].states, rtol=0, atol=1e-5)
    np.testing.assert_allclose(same[0][0].states, differ[0][0].states, rtol=0, atol=1e-5)  # same in any batch
    assert np.abs(differ[0][0].states - differ[1][0].states).max() > 1e-3
    with pytest.raises(RuntimeError, match="batch of 3 envs for 2 candidate noises"):
        PerEnvNoisePolicy(policy, torch.stack([a, b])).select_action(
            {"observation.state": torch.zeros(3, 6), "observation.environment_state": torch.zeros(3, 6)})
    with pytest.raises(ValueError, match=r"shape \[B, horizon, action_dim\]"):
        PerEnvNoisePolicy(policy, a)


def test_bad_input_is_named(results, tmp_path, capsys):
    base = ["search-curves", str(results), "--env", "reach-around", "--seed", str(SEED), "--out", str(tmp_path / "c"),
            "--no-progress"]
    cases = [
        (["--scene", "val1", "--budgets", "0", "8"], r"budget 0 must be an integer >= rollouts_per_candidate \(2\)"),
        (["--scene", "val1", "--methods", "z_fit", "adam"], r"unknown method\(s\) \['adam'\]"),
        (["--scene", "val1", "--score", "waypoints"], "reach-around scene val1 ships no way-points"),
        (["--scene", "val3", "--score", "waypoints", "--methods", "z_fit", "fit"],
         r"\['z_fit', 'fit'\] fit a demonstration"),
        (["--scene", "val1", "--rollouts", "0"], "rollouts must be an integer in 1..4000.*got 0"),
        (["--scene", "0"], "scene 0 has no adaptation"),
        (["--scene", "val9"], "ships no validation scene 'val9'"),
        (["--scene", "1"], r"test scene 1 got validation seed\(s\) 100: validation scenes \(val1, val2, \.\.\.\) go "
                           r"with seeds >= 100, test scenes \(1, 2, \.\.\.\) with seeds below"),
    ]
    for extra, match in cases:
        assert cli([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert __import__("re").search(match, err), (extra, err)
    assert cli(["search-curves", str(tmp_path), "--env", "reach-around", "--scene", "val1", "--seed", str(SEED),
                "--out", str(tmp_path / "c")]) == 2
    assert f"no trained pdp run at {tmp_path}/runs/pdp/seed{SEED}" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    # another env's folder (here still without results.json: named by its dataset) is refused before a demo is made
    demos = sorted((results / "data").iterdir())
    assert cli([*base[:3], "avoiding", *base[4:], "--scene", "val1"]) == 2
    assert f"{results} is a benchmark run of reach-around, not avoiding: give --env reach-around" in capsys.readouterr().err
    assert sorted((results / "data").iterdir()) == demos and not (tmp_path / "c").exists()


def test_a_second_search_into_a_held_folder_is_refused(results, tmp_path, capsys):
    """Two searches into one --out would lose each other's records (each rewrites the record file)."""
    from test_folder_lock import holder

    dest = tmp_path / "curves"
    proc = holder(dest)
    try:
        assert cli(["search-curves", str(results), "--env", "reach-around", "--scene", "val1", "--seed", str(SEED),
                    "--methods", "fit", "--rollouts", "1", "--out", str(dest), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert f"{dest} is being written by another process (pid {proc.pid}, benchmark since" in err, err
        assert not (dest / sc.RECORD).exists()
    finally:
        proc.kill()
        proc.wait()


def test_the_scene_demonstration_is_made_under_the_benchmark_folders_lock(results, tmp_path):
    """The fit's demonstration is written into the benchmark folder (where the benchmark keeps it): while a
    benchmark holds that folder, search-curves names it instead of racing it; once free, it makes the demo."""
    from test_folder_lock import holder

    from lerobot_pdp.benchmark.data import demo_root
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.folder_lock import FolderBusyError

    demo = demo_root(get_suite_env("reach-around"), results, "val2")
    assert not demo.exists()
    proc = holder(results)
    try:
        with pytest.raises(FolderBusyError, match=rf"{results} is being written by another process \(pid {proc.pid}, "):
            measure(results, tmp_path / "curves", scene="val2", methods=["fit"])
        assert not demo.exists()
    finally:
        proc.kill()
        proc.wait()
    measure(results, tmp_path / "curves", scene="val2", methods=["fit"])
    assert (demo / "meta" / "pdp_demo.json").is_file()


def test_cli_writes_the_record_with_its_command(results, tmp_path, capsys):
    dest = tmp_path / "fit_only"
    args = ["search-curves", str(results), "--env", "reach-around", "--scene", "val1", "--seed", str(SEED),
            "--methods", "fit", "--rollouts", "1", "--out", str(dest), "--no-progress"]
    assert cli(args) == 0
    assert "| fit |" in capsys.readouterr().out
    (rec,) = json.loads((dest / sc.RECORD).read_text())["records"].values()
    assert rec["command"] == (f"lerobot-pdp search-curves {results.name} --env reach-around --scene val1 --seed 100 "
                              "--budgets 16 32 64 128 256 512 --rollouts 1 --rollouts-per-candidate 2 --score success "
                              "--confirm-rollouts 6 --methods fit")
    assert rec["points"][0]["n"] == 1 and rec["settings"]["max_episode_steps"] == 200


def test_cli_finish_is_the_same_score_as_lerobot_pdp_search_finish(results, tmp_path, capsys):
    """``--score waypoints --finish`` (the spelling of ``lerobot-pdp search``) records ``waypoints_finish``."""
    dest = tmp_path / "finish"
    base = ["search-curves", str(results), "--env", "reach-around", "--scene", "val3", "--seed", str(SEED),
            "--methods", "z_modes", "--budgets", "4", "--rollouts", "1", "--radius", "0.08", "--out", str(dest),
            "--no-progress"]
    assert cli([*base, "--finish"]) == 2
    assert "use it with --score waypoints, not --score success" in capsys.readouterr().err
    assert cli([*base, "--score", "waypoints", "--finish"]) == 0
    (rec,) = json.loads((dest / sc.RECORD).read_text())["records"].values()
    assert "--score waypoints_finish" in rec["command"] and rec["settings"]["objective"]["finish"] is True


def test_a_budget_short_of_one_confirmed_candidate_is_warned(caplog):
    """With confirmation on, one candidate and its confirmation cost rollouts_per_candidate + confirm_rollouts: a
    budget point below that is the first candidate only, said before the search runs."""
    import logging

    from lerobot_pdp.benchmark.search_curves import check_request

    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.benchmark.search_curves"):
        check_request(None, [16, 4], 40, "success", 2, "val3", confirm_rollouts=6)
        assert "budget(s) [4] pay for less than one candidate and its confirmation (2 + 6 rollouts)" in caplog.text
        caplog.clear()
        check_request(None, [4], 40, "success", 2, "val3", confirm_rollouts=0)
    assert not caplog.records
