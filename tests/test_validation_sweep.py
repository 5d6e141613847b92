"""``benchmark --split validation --validate``: every method's candidate samplers and adaptation settings are
evaluated on the validation split only (real lerobot-train runs, real rollouts), with as many candidates per
method, and the choice is the best mean success (ties: the default, listed first)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from lerobot_pdp.benchmark import settings, validation
from lerobot_pdp.benchmark.protocol import run_benchmark
from lerobot_pdp.benchmark.settings import BenchmarkConfig, split_scenes


@pytest.mark.slow
def test_validate_tiny(tmp_path, monkeypatch, one_torch_thread):
    import os

    # the in-process evaluations and the --jobs 2 workers below on one thread each, whatever the machine's
    # cores: the rerun must reproduce the numbers bit for bit, and float sums split over threads differ
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.delitem(settings.FROZEN, ("reach-around", "full"))  # shipped choices: the full budget, not this run
    # a shorter candidate list keeps the test quick; the shipped lists are checked below
    monkeypatch.setattr(validation, "SAMPLER_CANDIDATES", ((4, "leading"), (4, "trailing")))
    monkeypatch.setattr(validation, "ADAPT_CANDIDATES", {"fit_latent": ({}, {"steps": 0}),
                                                         "noise": ({}, {"steps": 3}),
                                                         "finetune": ({}, {"lr": 1e-3})})
    scenes = split_scenes("reach-around", "validation")
    cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "val", seeds=[100], rollouts=2,
                          methods=["pdp", "dp", "bc"], steps=20, episodes_per_mode=1, scenes=scenes,
                          split="validation", validate=True, figures=False, inference_steps=4)
    res = run_benchmark(cfg)
    val = json.loads((tmp_path / "val" / "validation.json").read_text())
    assert val["split"] == "validation" and set(val["methods"]) == {"pdp", "dp", "bc"}
    for name, rec in val["methods"].items():
        assert rec["seeds"] == [100] and rec["scenes"] == [str(s) for s in scenes]
        assert len(rec["sampler"]) == (0 if name == "bc" else 2) and len(rec["adapt"]) == 2
        for row in rec["sampler"] + rec["adapt"]:
            assert all(s in rec["scenes"] for s in row["success"])  # validation scenes only, never 1-3
            assert all(0.0 <= x <= 1.0 for xs in row["success"].values() for x in xs)
        # the choice follows the rule of validation.choose (2 rollouts x scenes x 1 seed behind each score)
        assert rec["chosen"]["adapt"] == rec["adapt"][validation.choose(rec["adapt"], 2 * 4)]["adapt"]
        if rec["sampler"]:
            assert rec["sampler"][0]["sampler"] == [4, "leading"]  # the run's own sampler is the default
            assert rec["chosen"]["sampler"] == rec["sampler"][validation.choose(rec["sampler"], 2 * 5)]["sampler"]
            # adaptation candidates are evaluated with the chosen sampler
            assert all(r["sampler"] == rec["chosen"]["sampler"] for r in rec["adapt"])
        evals = sorted(p.name for p in (tmp_path / "val" / "runs" / name / "seed100" / "validation").glob("eval_*"))
        # the default candidate is the protocol's own eval.json, not a second evaluation
        assert len(evals) == len(rec["sampler"]) + len(rec["adapt"]) - (2 if rec["sampler"] else 1)
        last = rec["adapt"][-1]
        made = json.loads((tmp_path / "val" / "runs" / name / "seed100" / "validation" / f"eval_{last['tag']}.json")
                          .read_text())
        assert made["adapt"] == last["adapt"] != {} and set(made["scenes"]) == set(map(str, scenes[1:]))
    assert res["validation"] == {n: r["chosen"] for n, r in val["methods"].items()}
    md = (tmp_path / "val" / "validation.md").read_text()
    assert "| sampler | s4-trailing |" in md and "Chosen:" in md
    # a second call reuses every cached candidate evaluation
    stamps = {p: p.stat().st_mtime for p in (tmp_path / "val" / "runs").rglob("validation/eval_*.json")}
    run_benchmark(cfg)
    assert stamps == {p: p.stat().st_mtime for p in stamps}
    # --jobs 2: each stage's candidates are evaluated in worker processes (seeded rollouts: the same numbers)
    for p in stamps:
        p.unlink()
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "jobs": 2}))
    assert all(p.is_file() for p in stamps)
    assert json.loads((tmp_path / "val" / "validation.json").read_text()) == val
    # a changed candidate list: --reuse-validation evaluates only the new candidate, every other row of the
    # earlier record stands once the runs' own evaluations reproduce it
    before = tmp_path / "validation_before.json"
    before.write_text(json.dumps(val))
    monkeypatch.setitem(validation.ADAPT_CANDIDATES, "fit_latent", ({}, {"steps": 1}))
    again = run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "reuse_validation": before}))
    val2 = json.loads((tmp_path / "val" / "validation.json").read_text())
    assert val2["reused_from"] == str(before) and again["validation"]["dp"] == val["methods"]["dp"]["chosen"]
    pdp = val2["methods"]["pdp"]
    assert [r.get("reused", False) for r in pdp["adapt"]] == [True, False]
    assert all(r["reused"] for r in pdp["sampler"] + val2["methods"]["bc"]["adapt"])
    assert pdp["adapt"][1]["adapt"] == {"steps": 1} and pdp["reuse_check"]["compared"]
    new_tag = validation.candidate_tag(tuple(pdp["chosen"]["sampler"]), {"steps": 1})
    assert (tmp_path / "val" / "runs" / "pdp" / "seed100" / "validation" / f"eval_{new_tag}.json").is_file()
    assert "† reused from" in (tmp_path / "val" / "validation.md").read_text()
    # a record of another checkpoint: nothing of it is reused, every candidate is evaluated (here from the
    # cache files), and the record says why
    other = json.loads(before.read_text())
    other["methods"]["bc"]["adapt"][0]["success"]["val1"] = [0.123]
    before.write_text(json.dumps(other))
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["bc"], "reuse_validation": before}))
    bc = json.loads((tmp_path / "val" / "validation.json").read_text())["methods"]["bc"]
    assert "not the same checkpoint" in bc["reuse_refused"] and not any(r.get("reused") for r in bc["adapt"])
    assert bc["chosen"] == val["methods"]["bc"]["chosen"]
    with pytest.raises(ValueError, match="--reuse-validation reuses"):
        run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "validate": False, "reuse_validation": before}))
    with pytest.raises(ValueError, match="--jobs 2: processes for --validate"):
        run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "jobs": 2, "validate": False}))
    # a frozen choice (settings.FROZEN) is what the protocol's own evaluation samples and adapts with, unless
    # the command line names a sampler; recorded in results.json
    frozen = {"bc": {"adapt": {"lr": 1e-3}}, "pdp": {"sampler": [4, "trailing"], "adapt": {"steps": 0}}}
    monkeypatch.setitem(settings.FROZEN, ("reach-around", "full"), frozen)
    res = run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["pdp", "bc"], "validate": False,
                                           "inference_steps": None}))
    made = {m: json.loads((tmp_path / "val" / "runs" / m / "seed100" / "eval.json").read_text()) for m in ("pdp", "bc")}
    assert made["bc"]["adapt"] == {"lr": 1e-3} == res["methods"]["bc"]["adapt"]
    assert (made["pdp"]["inference_steps"], made["pdp"]["timestep_spacing"], made["pdp"]["adapt"]) == (4, "trailing",
                                                                                                        {"steps": 0})
    assert res["frozen"]["methods"] == frozen
    run_benchmark(BenchmarkConfig(**{**cfg.__dict__, "methods": ["pdp"], "validate": False, "inference_steps": 3}))
    assert json.loads((tmp_path / "val" / "runs" / "pdp" / "seed100" / "eval.json").read_text())["inference_steps"] == 3
    # never on the test split
    with pytest.raises(ValueError, match="validation split only"):
        run_benchmark(BenchmarkConfig(env="reach-around", out=tmp_path / "t", seeds=[0], validate=True))


def test_every_method_gets_as_many_candidates():
    """Same tuning budget: as many adaptation candidates per method, each list led by the default."""
    sizes = {len(v) for v in validation.ADAPT_CANDIDATES.values()}
    assert sizes == {6} and all(v[0] == {} for v in validation.ADAPT_CANDIDATES.values())
    assert len(set(validation.SAMPLER_CANDIDATES)) == len(validation.SAMPLER_CANDIDATES)
    assert validation.candidate_tag((20, "leading"), {"steps": 300, "lr": 0.2}) == "s20-leading_lr0.2_steps300"


def _run(tmp_path, seed, success):
    run = tmp_path / f"seed{seed}"
    run.mkdir(parents=True)
    (run / "eval.json").write_text(json.dumps({"inference_steps": 20, "timestep_spacing": "leading", "adapt": {},
                                               "scenes": {s: {"success": v} for s, v in success.items()}}))
    return run


def test_reused_rows_need_the_same_checkpoint(tmp_path):
    """``--reuse-validation``: an earlier record's rows stand for retrained runs only if each run's own
    evaluation reproduces that record exactly; another checkpoint, seed list or scene list is refused."""
    row = {"tag": "s20-leading", "success": {"0": [1.0, 0.9], "val1": [0.5, 0.25]}}
    rec = {"seeds": [100, 101], "scenes": ["0", "val1"], "sampler": [row], "adapt": [{**row, "success": {"val1": [0.5, 0.25]}}]}
    runs = {100: _run(tmp_path, 100, {"0": 1.0, "val1": 0.5}), 101: _run(tmp_path, 101, {"0": 0.9, "val1": 0.25})}
    check = validation.check_reuse("pdp", runs, rec, "old.json", [0, "val1"])
    assert check["source"] == "old.json" and len(check["compared"]) == 6  # 2 seeds x (2 sampler + 1 adapt scenes)
    other = {**runs, 101: _run(tmp_path / "b", 101, {"0": 0.9, "val1": 0.3})}
    with pytest.raises(ValueError, match=r"seed 101 scene val1 \(s20-leading\) succeeds 0.300.*0.250: not the same checkpoint"):
        validation.check_reuse("pdp", other, rec, "old.json", [0, "val1"])
    with pytest.raises(ValueError, match="validated on seeds"):
        validation.check_reuse("pdp", {100: runs[100]}, rec, "old.json", [0, "val1"])
    with pytest.raises(ValueError, match="no candidate of pdp matches"):
        validation.check_reuse("pdp", runs, {**rec, "sampler": [], "adapt": []}, "old.json", [0, "val1"])


def test_a_wrong_reuse_record_is_refused_before_training(tmp_path):
    """``--reuse-validation`` names a file that is missing, not JSON, not a validation record, or of another env /
    rollout count / observation variant: refused by name when the run starts, before any dataset or training."""
    good = {"env": "reach-around", "split": "validation", "rollouts": 40, "methods": {}}
    bad = {"missing.json": None, "notjson.json": "{", "list.json": "[]",
           "other_env.json": json.dumps({**good, "env": "avoiding"}),
           "other_rollouts.json": json.dumps({**good, "rollouts": 20}),
           "camera.json": json.dumps({**good, "observation": {"obs": "images", "camera": "oblique", "image_size": 64}})}
    why = {"missing.json": "no such file", "notjson.json": "is not JSON", "list.json": "not a validation record",
           "other_env.json": "env is 'avoiding', this run's is 'reach-around'",
           "other_rollouts.json": "rollouts is 20, this run's is 40",
           "camera.json": "observation is {'obs': 'images'.*this run's is None"}
    for name, text in bad.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "out", seeds=[100], split="validation", validate=True,
                              scenes=split_scenes("reach-around", "validation"), reuse_validation=tmp_path / name)
        with pytest.raises(ValueError, match=f"--reuse-validation {tmp_path / name}.*{why[name]}"):
            run_benchmark(cfg)
    assert not (tmp_path / "out").exists()  # refused before anything was written
    (tmp_path / "good.json").write_text(json.dumps(good))
    assert validation.load_reuse_record(replace(cfg, reuse_validation=tmp_path / "good.json"), "reach-around") == good
    camera = json.loads((tmp_path / "camera.json").read_text())  # a camera run reuses a camera record only
    camera_cfg = replace(cfg, obs="images", camera="oblique", image_size=64)
    assert validation.load_reuse_record(replace(camera_cfg, reuse_validation=tmp_path / "camera.json"),
                                        "reach-around") == camera
    with pytest.raises(ValueError, match="observation is None, this run's is {'obs': 'images'"):
        validation.load_reuse_record(replace(camera_cfg, reuse_validation=tmp_path / "good.json"), "reach-around")


def test_a_camera_validation_reuses_a_camera_record_and_records_what_it_observed(tmp_path):
    """``validate`` of the camera variant reads a camera record (its methods not run here are carried over) and
    writes ``observation`` into the new record; a state record is refused there by name."""
    from lerobot_pdp.benchmark.settings import CAMERAS, IMAGE_SIZE, methods_for
    from lerobot_pdp.envs import get_suite_env

    suite = get_suite_env("reach-around").with_camera(CAMERAS["reach-around"], IMAGE_SIZE)
    cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "val", seeds=[100], rollouts=20, split="validation",
                          validate=True, scenes=split_scenes("reach-around", "validation"), obs="images",
                          camera=CAMERAS["reach-around"])
    dp = {"seeds": [100], "scenes": ["0"], "sampler": [], "adapt": [], "chosen": {"sampler": None, "adapt": {}}}
    record = {"env": "reach-around", "split": "validation", "rollouts": 20, "observation": cfg.observation(),
              "sampler_candidates": [list(c) for c in validation.SAMPLER_CANDIDATES],
              "adapt_candidates": {k: list(v) for k, v in validation.ADAPT_CANDIDATES.items()}, "methods": {"dp": dp}}
    (tmp_path / "camera.json").write_text(json.dumps(record))
    (tmp_path / "state.json").write_text(json.dumps({k: v for k, v in record.items() if k != "observation"}))
    (tmp_path / "val").mkdir()
    out = validation.validate(replace(cfg, reuse_validation=tmp_path / "camera.json"), suite, methods_for(suite), {},
                              [])
    assert out["observation"] == {"obs": "images", "camera": "oblique", "image_size": IMAGE_SIZE}
    assert out["methods"] == {"dp": dp}
    assert json.loads((tmp_path / "val" / "validation.json").read_text()) == out
    with pytest.raises(ValueError, match=f"--reuse-validation {tmp_path / 'state.json'}: observation is None"):
        validation.validate(replace(cfg, reuse_validation=tmp_path / "state.json"), suite, methods_for(suite), {}, [])


def test_a_setting_changes_only_on_evidence():
    """The default (row 0) stays unless the best candidate beats it by more than one standard error."""
    rows = [{"score": 0.60}, {"score": 0.62}, {"score": 0.55}]
    assert validation.choose(rows, 120) == 0  # +2 points over 120 rollouts: noise (se ~4.5 points)
    rows[1]["score"] = 0.70
    assert validation.choose(rows, 120) == 1
    rows[2]["score"] = 0.70
    assert validation.choose(rows, 120) == 1  # ties: the earlier
    assert validation.choose([{"score": 1.0}, {"score": 1.0}], 40) == 0


def test_a_training_setting_is_chosen_on_validation_runs_by_the_same_rule():
    """``choose_training_setting``: every scene (scene 0 too) and seed count; the current setting (first) stays
    unless beaten by more than one standard error; test runs and unlike runs are refused."""
    def res(rates, split="validation", rollouts=40, film="mlp"):
        scenes = {f"scene{'' if i == 0 else '_val'}{i if i else 0}": {"success": [r]} for i, r in enumerate(rates)}
        return {"env": "avoiding", "split": split, "rollouts": rollouts, "film": film, "train": {"steps": 8000},
                "methods": {"pdp": {"seeds": [100], **scenes}}}

    mlp = res([1.0, 0.9, 0.95, 0.05, 0.0])  # 58 %
    close = res([1.0, 0.95, 0.95, 0.1, 0.0], film="affine")  # 60 %: +2 points over 200 rollouts is noise
    rec = validation.choose_training_setting("pdp", "film", {"mlp": mlp, "affine": close})
    assert rec["chosen"] == "mlp" and [round(r["score"], 2) for r in rec["candidates"]] == [0.58, 0.6]
    assert rec["scenes"] == ["scene0", "scene_val1", "scene_val2", "scene_val3", "scene_val4"]
    better = res([1.0, 0.95, 0.95, 0.5, 0.4], film="affine")
    assert validation.choose_training_setting("pdp", "film", {"mlp": mlp, "affine": better})["chosen"] == "affine"
    with pytest.raises(ValueError, match="affine: a 'test' run"):
        validation.choose_training_setting("pdp", "film", {"mlp": mlp, "affine": res([1.0] * 5, split="test")})
    with pytest.raises(ValueError, match="compare like with like"):
        validation.choose_training_setting("pdp", "film", {"mlp": mlp, "affine": res([1.0] * 5, rollouts=20)})
    with pytest.raises(ValueError, match="no dp in its results"):
        validation.choose_training_setting("dp", "film", {"mlp": mlp})
    summed = res([1.0, 0.9, 0.95, 0.05, 0.0]) | {"rec_reduction": "sum"}  # files before the option: the mean
    rows = validation.choose_training_setting("pdp", "rec_reduction", {"mean": mlp, "sum": summed})["candidates"]
    assert [r["rec_reduction"] for r in rows] == ["mean", "sum"]


@pytest.mark.slow
def test_teach_tiny(tmp_path, monkeypatch):
    """``benchmark --teach`` on the validation split: every method taught the zero-mode scene's route with each
    candidate (PDP a new mode, BC / DP fine-tuned with rehearsal), the new route and scene 0 measured beside the
    untaught checkpoint's scene 0 (real lerobot-train runs, real rollouts)."""
    from lerobot_pdp.benchmark import teaching

    monkeypatch.setattr(teaching, "TEACH_CANDIDATES", ({"steps": 3, "lr": 1e-4},))
    monkeypatch.setattr(teaching, "TEACH_EXTRA", {})
    # BC is taught by the same function as DP (finetune_with_rehearsal): two methods keep the test short
    cfg = BenchmarkConfig(env="avoiding", out=tmp_path / "teach", seeds=[100], rollouts=2, methods=["pdp", "dp"],
                          steps=20, episodes_per_mode=1, scenes=(0, "val4"), split="validation", figures=False,
                          inference_steps=4, teach=True)
    res = run_benchmark(cfg)
    record = json.loads((tmp_path / "teach" / "teach.json").read_text())
    assert res["teach"] == record and record["rollouts_scene0"] == 24  # 2 rollouts, one per mode of the 24
    assert set(record["runs"]) == {"pdp", "dp"}
    for name, seeds in record["runs"].items():
        run = seeds["100"]["runs"]["val4 steps=3 lr=0.0001"]
        assert run["new_route"]["n"] == 2 and run["scene0"]["n"] == 24 and run["teach_seconds"] > 0
        assert seeds["100"]["base_scene0"]["n"] == 24
        if name == "pdp":  # the new mode, steered to; scene 0 steered to the 24 old modes only
            assert run["mode"] == 24 and "steer_accuracy" in run["scene0"]
    assert "| pdp | 100 | val4 | 3 | 0.0001 |" in (tmp_path / "teach" / "teach.md").read_text()
    with pytest.raises(ValueError, match="no zero-mode scene in the validation split"):
        run_benchmark(replace(cfg, env="reach-around", scenes=split_scenes("reach-around", "validation"),
                              out=tmp_path / "teach_ra"))  # its own folder: the avoiding run's is refused first
    with pytest.raises(ValueError, match=r"evaluate at least one of them too \(--scenes\)"):
        run_benchmark(replace(cfg, scenes=(0, "val1")))


def test_teaching_is_chosen_for_the_new_route_among_settings_that_keep_scene_0():
    from lerobot_pdp.benchmark.teaching import choose_teaching

    def run(new: float, kept: float) -> dict:
        return {"new_route": {"success": new}, "scene0": {"success": kept}}

    base = {"success": 0.9}
    runs = {"val4 steps=300 lr=0.0001": run(0.2, 0.9), "val4 steps=1000 lr=0.001": run(1.0, 0.8),
            "val4 steps=3000 lr=0.0001": run(0.7, 0.86), "val4 steps=1000 lr=0.0001": run(0.7, 0.95)}
    # 1000 at 1e-3 takes the route but loses 10 points of scene 0; of the two at 70 %, the first listed
    assert choose_teaching(runs, base) == ("steps=3000 lr=0.0001", True)
    # none keeps scene 0: the best new route among all, said so
    assert choose_teaching({"val4 steps=1": run(0.2, 0.5), "val4 steps=2": run(0.4, 0.1)}, base) == ("steps=2", False)


def test_teaching_table_says_what_was_chosen_on_validation_and_frozen_on_test():
    from lerobot_pdp.benchmark.teaching import teach_markdown

    row = {"scene": 4, "steps": 3000, "lr": 1e-4, "teach_seconds": 1.0, "new_route": {"success": 0.5},
           "scene0": {"success": 0.9, "coverage": 1.0, "steer_accuracy": 0.9}}
    res = {"base_scene0": {"success": 0.9}, "runs": {"4 steps=3000 lr=0.0001": row}, "chosen": "steps=3000 lr=0.0001",
           "chosen_keeps_scene0": True}
    record = {"env": "avoiding", "split": "test", "rollouts": 2, "rollouts_scene0": 24, "batch_size": 64,
              "demo_share": 0.25, "runs": {"pdp": {"6": res}}}
    md = teach_markdown(record)
    assert "| pdp | 6 | 4 | 3000 | 0.0001 |" in md and "with its frozen setting steps=3000 lr=0.0001" in md
    assert "Chosen for" not in md
    assert "Chosen for pdp (seed 6)" in teach_markdown({**record, "split": "validation"})


def test_frozen_teaching_settings_are_what_the_committed_records_chose():
    from pathlib import Path

    from lerobot_pdp.benchmark import teaching

    root = Path(__file__).resolve().parents[1]
    assert set(settings.TEACH_FROZEN) == set(settings.TEACH_RECORDS)
    for key, files in settings.TEACH_RECORDS.items():
        chosen = {}
        for rel in files:
            record = json.loads((root / rel).read_text())
            assert record["env"] == key[0] and record["split"] == "validation"
            for name, seeds in record["runs"].items():
                (res,) = seeds.values()
                cand = next(c for c in teaching.TEACH_CANDIDATES + teaching.TEACH_EXTRA.get(name, ())
                            if res["chosen"] == f"steps={c['steps']} lr={c['lr']:g}"
                            + (f" latent={c['latent']}" if "latent" in c else ""))
                chosen[name] = cand
        assert settings.TEACH_FROZEN[key] == chosen
