"""results.json / results.md aggregation over seeds (pure functions; the protocol tests run the real thing)."""

import json
from pathlib import Path

import pytest

from lerobot_pdp.benchmark.data import ensure_dataset
from lerobot_pdp.benchmark.results import aggregate, results_markdown
from lerobot_pdp.benchmark.settings import BenchmarkConfig, TrainSettings
from lerobot_pdp.envs import get_suite_env


def _run(rates: list[float]) -> dict:
    return {"scenes": {str(s): {"success": r, "collision": 0.0} for s, r in enumerate(rates)}}


def test_the_frozen_record_is_the_one_taken_when_the_run_started(monkeypatch):
    """results.json's ``frozen`` is what the run started with (run_benchmark takes it first): a validation record
    or FROZEN entry replaced while a long run goes on does not relabel its numbers."""
    from lerobot_pdp.benchmark import results, settings
    from lerobot_pdp.benchmark.results import frozen_record

    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0])
    start = frozen_record("reach-around", cfg)
    assert start["methods"] == settings.FROZEN[("reach-around", "full")]
    assert start["validation"]["pdp"]["chosen"]["adapt"] == start["methods"]["pdp"]["adapt"]
    monkeypatch.setitem(results.FROZEN, ("reach-around", "full"), {"pdp": {"adapt": {"steps": 7}}})
    res = aggregate("reach-around", cfg, {"pdp": {0: _run([1.0] * 4)}}, {}, TrainSettings(steps=10), 10, start)
    assert res["frozen"] == start
    now = aggregate("reach-around", cfg, {"pdp": {0: _run([1.0] * 4)}}, {}, TrainSettings(steps=10), 10)["frozen"]
    assert now["methods"] == {"pdp": {"adapt": {"steps": 7}}}  # without it: read when aggregating


def test_mean_and_std_over_seeds_in_json_and_table():
    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0, 1])
    per_run = {"pdp": {0: _run([1.0, 0.9, 1.0, 0.8]), 1: _run([1.0, 0.7, 1.0, 1.0])},
               "dp": {0: _run([0.5, 0.0, 1.0, 0.0])}}  # a method with one finished seed so far
    init = {0: {"encoder@0": 0.5, "random@0": 0.0,
                "per_scene": {"encoder@0": {"1": 0.5, "3": 0.5}, "random@0": {"1": 0.0, "3": 0.0}}},
            1: {"encoder@0": 0.7, "random@0": 0.1,
                "per_scene": {"encoder@0": {"1": 1.0, "3": 0.4}, "random@0": {"1": 0.0, "3": 0.2}}}}
    res = aggregate("reach-around", cfg, per_run, init, TrainSettings(steps=10), 10)
    assert res["train"]["steps"] == 10 and res["train"]["warmup_steps"] == 1  # as lerobot-train got it (capped)
    assert aggregate("reach-around", cfg, per_run, init, TrainSettings(steps=10), 6000)["train"]["warmup_steps"] == 100
    s1 = res["methods"]["pdp"]["scene1"]
    assert s1["success"] == [0.9, 0.7] and s1["mean"] == pytest.approx(0.8) and s1["std"] == pytest.approx(0.1)
    assert res["methods"]["pdp"]["shifted_avg"] == pytest.approx((0.8 + 1.0 + 0.9) / 3)
    assert res["methods"]["dp"]["scene0"]["success"] == [0.5]
    assert res["init_ablation"]["encoder@0"]["mean"] == pytest.approx(0.6)
    assert res["init_ablation"]["encoder@0"]["scenes"] == pytest.approx({"1": 0.75, "3": 0.45})
    md = results_markdown(res)
    assert "| pdp | 100.0 ± 0.0 | 80.0 ± 10.0 | 100.0 ± 0.0 | 90.0 ± 10.0 | 90.0 |" in md
    assert "| dp (seeds [0]) | 50.0 | 0.0 | 100.0 | 0.0 |" in md  # one seed: no std; its seed named
    assert "| warm (encoder) | 60.0 ± 10.0 |" in md and "| random | 5.0 ± 5.0 |" in md
    assert "| init @ fitting steps | Shift 1 | Shift 3 |" in md  # where each initialisation wins or loses
    assert "| warm (encoder) @ 0 | 75.0 | 45.0 |" in md and "| random @ 0 | 0.0 | 10.0 |" in md
    assert "| Shifted avg |" in md  # the test scenes 1-3: the protocol's average, named as such

    # a run of some scenes only (--scenes 0 1): its average says what it averages
    part = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0], scenes=[0, 1])
    md = results_markdown(aggregate("reach-around", part, {"pdp": {0: _run([1.0, 0.5])}}, {}, TrainSettings(steps=10), 10))
    assert "| Original (scene 0) | Shift 1 | Shifted avg (shift 1) |" in md and "| pdp | 100.0 | 50.0 | 50.0 |" in md


def test_the_device_each_evaluation_ran_on_is_recorded_and_merged():
    """Cached evaluations are reused on any device: the table says where each method's evaluations ran, and
    which CPU the run was on (merged runs: every CPU)."""
    from lerobot_pdp.benchmark.machine import cpu_model
    from lerobot_pdp.benchmark.results import merge_results

    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0, 1])
    gpu = {**_run([1.0, 1.0, 1.0, 1.0]), "device": "cuda"}
    cpu = {**_run([1.0, 0.5, 1.0, 1.0]), "device": "cpu"}
    res = aggregate("reach-around", cfg, {"pdp": {0: cpu, 1: cpu}, "dp": {0: gpu, 1: cpu}}, {},
                    TrainSettings(steps=10), 10)
    assert res["methods"]["pdp"]["eval_devices"] == ["cpu"] and res["methods"]["dp"]["eval_devices"] == ["cpu", "cuda"]
    assert "Evaluated on: pdp cpu, dp cpu/cuda." in results_markdown(res)
    assert res["cpu"] == cpu_model() != "" and f"CPU: {cpu_model()}." in results_markdown(res)
    old = aggregate("reach-around", BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[2]),
                    {"pdp": {2: _run([1.0, 1.0, 1.0, 1.0])}, "dp": {2: _run([0.0, 0.0, 0.0, 0.0])}}, {},
                    TrainSettings(steps=10), 10)  # caches from before the device was recorded
    assert old["methods"]["pdp"]["eval_devices"] == ["unrecorded"]
    del old["cpu"]  # a results.json from before the CPU was recorded
    merged = merge_results([("a", res), ("b", old)])
    assert set(merged["cpu"].split("/")) == {cpu_model(), "unrecorded"}
    assert merged["methods"]["dp"]["eval_devices"] == ["cpu", "cuda", "unrecorded"]
    assert "Evaluated on: pdp cpu/unrecorded, dp cpu/cuda/unrecorded." in results_markdown(merged)


def test_reusing_a_dataset_of_another_size_is_refused(tmp_path):
    """Runs trained on 3 demos/mode must not land in one table with runs on 6: a mismatch names both sizes."""
    suite = get_suite_env("reach-around")
    meta = tmp_path / "data" / f"{suite.scene_key}_scene0" / "meta"
    meta.mkdir(parents=True)
    (meta / "info.json").write_text(json.dumps({"total_episodes": 3 * suite.n_modes}))
    assert ensure_dataset(suite, tmp_path, TrainSettings(steps=1, episodes_per_mode=3)) == meta.parent
    with pytest.raises(ValueError, match=f"holds {3 * suite.n_modes} episodes but this benchmark needs "
                                         f"{6 * suite.n_modes}"):
        ensure_dataset(suite, tmp_path, TrainSettings(steps=1, episodes_per_mode=6))


@pytest.mark.parametrize("steps", [0, 21])
def test_inference_steps_outside_1_to_k_is_refused_before_anything_is_written(tmp_path, steps):
    from lerobot_pdp.benchmark.protocol import run_benchmark

    cfg = BenchmarkConfig(env="reach-around", out=tmp_path / "bench", seeds=[0], inference_steps=steps)
    with pytest.raises(ValueError, match=rf"inference_steps must be in 1\.\.20 .*got {steps}"):
        run_benchmark(cfg)
    assert not (tmp_path / "bench").exists()


def _results(seeds: list[int], per_method: dict[str, dict[int, list[float]]], init: dict | None = None,
             **cfg_kw) -> dict:
    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=seeds, **cfg_kw)
    per_run = {m: {s: _run(r) for s, r in runs.items()} for m, runs in per_method.items()}
    return aggregate("reach-around", cfg, per_run, init or {}, TrainSettings(steps=10), 10)


def _init(scene_rates: dict[str, float]) -> dict:
    """One seed's init-ablation result with the same per-scene rates for every (init, steps)."""
    keys = [f"{i}@{n}" for i in ("encoder", "random") for n in (0, 10, 100)]
    mean = sum(scene_rates.values()) / len(scene_rates)
    return {**{k: mean for k in keys}, "per_scene": {k: dict(scene_rates) for k in keys}}


def test_merging_runs_of_different_seeds_equals_one_run_of_all_seeds():
    """Seeds run in two folders merge into the table a single run over all seeds would have written."""
    from lerobot_pdp.benchmark.results import merge_results

    s0 = {"pdp": {0: [1.0, 0.9, 1.0, 0.8]}, "dp": {0: [0.5, 0.0, 1.0, 0.0]}}
    s12 = {"pdp": {1: [1.0, 0.7, 1.0, 1.0], 2: [0.9, 0.8, 0.6, 1.0]}, "dp": {1: [0.4, 0.1, 0.9, 0.2]}}
    init = {0: _init({"1": 1.0, "2": 0.5, "3": 0.0}), 1: _init({"1": 0.5, "2": 0.5, "3": 0.5}),
            2: _init({"1": 0.0, "2": 1.0, "3": 1.0})}
    whole = _results([0, 1, 2], {m: {**s0[m], **s12[m]} for m in s0}, init)
    merged = merge_results([("b", _results([1, 2], s12, {1: init[1], 2: init[2]})),
                            ("a", _results([0], s0, {0: init[0]}))])
    for k, entry in whole["init_ablation"].items():  # seed-weighted, per scene too
        assert merged["init_ablation"][k]["mean"] == pytest.approx(entry["mean"])
        assert merged["init_ablation"][k]["scenes"] == pytest.approx(entry["scenes"])
    assert merged["seeds"] == [0, 1, 2] and merged["merged_from"] == ["b", "a"]
    for key in ("frozen", "scenes", "device", "cpu", "split"):  # what was frozen survives the merge
        assert merged[key] == whole[key], key
    for m in ("pdp", "dp"):
        assert merged["methods"][m]["seeds"] == whole["methods"][m]["seeds"]
        for key in ("scene0", "scene1", "scene2", "scene3"):
            for field_ in ("success", "mean", "std", "collision"):
                assert merged["methods"][m][key][field_] == pytest.approx(whole["methods"][m][key][field_])
        assert merged["methods"][m]["shifted_avg"] == pytest.approx(whole["methods"][m]["shifted_avg"])
    md = results_markdown(merged)
    assert "| dp (seeds [0, 1]) | 45.0 ± 5.0 |" in md  # a method missing a seed says which it has
    assert "| pdp | 96.7 ± 4.7 |" in md and "Merged from: b, a." in md


def test_merging_refuses_a_seed_twice_and_other_settings_naming_the_files():
    from lerobot_pdp.benchmark.results import merge_results

    a = _results([0], {"pdp": {0: [1.0, 1.0, 1.0, 1.0]}})
    with pytest.raises(ValueError, match="pdp seed 0 is in both a and b"):
        merge_results([("a", a), ("b", a)])
    other = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}}, rollouts=20)
    with pytest.raises(ValueError, match="b: rollouts is 20 but a has 40"):
        merge_results([("a", a), ("b", other)])
    longer = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}})
    longer["train"] = {**longer["train"], "steps": longer["train"]["steps"] + 1}
    with pytest.raises(ValueError, match=r"b: train is \{'steps': \d+\} but a has \{'steps': \d+\}"):  # the field
        merge_results([("a", a), ("b", longer)])
    with pytest.raises(ValueError, match="at least two"):
        merge_results([("a", a)])
    refrozen = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}})
    refrozen["frozen"] = {**refrozen["frozen"], "methods": {**refrozen["frozen"]["methods"],
                                                            "pdp": {"sampler": [5, "leading"]}}}
    with pytest.raises(ValueError, match="b: frozen is .* for pdp but a has"):  # other frozen settings: not one table
        merge_results([("a", a), ("b", refrozen)])
    # a run frozen before another method was validated merges with that method's later runs: each method's
    # own settings agree, and the merged record holds both
    early = _results([0], {"vqbet": {0: [0.0, 1.0, 0.0, 0.0]}})
    early["frozen"] = {"methods": {"vqbet": {"adapt": {"steps": 300}}}, "validation_record": "v.json"}
    later = _results([0], {"pdp": {0: [1.0, 1.0, 1.0, 1.0]}})
    later["frozen"] = {"methods": {"vqbet": {"adapt": {"steps": 300}}, "pdp": {"sampler": [5, "trailing"]}},
                       "validation_record": "v.json"}
    both = merge_results([("early", early), ("later", later)])
    assert both["frozen"] == later["frozen"] and sorted(both["methods"]) == ["pdp", "vqbet"]
    changed = later | {"frozen": {**later["frozen"], "methods": {"vqbet": {"adapt": {"steps": 30}}}}}
    with pytest.raises(ValueError, match="later: frozen is .* for vqbet but early has"):
        merge_results([("early", early), ("later", changed)])
    with pytest.raises(ValueError, match="later: frozen validation_record is 'w.json' but early has 'v.json'"):
        merge_results([("early", early), ("later", later | {"frozen": {**later["frozen"], "validation_record": "w.json"}})])
    unfrozen = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}})  # pdp ran without a frozen setting
    unfrozen["frozen"] = {"validation_record": "v.json"}
    with pytest.raises(ValueError, match="frozen is .* for pdp but"):
        merge_results([("later", later), ("unfrozen", unfrozen)])
    affine = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}}, film="affine")
    assert a["film"] == "mlp" and affine["film"] == "affine"  # the env's form, else --film's
    with pytest.raises(ValueError, match="b: PDP's FiLM form is 'affine' but a has 'mlp'"):
        merge_results([("a", a), ("b", affine)])
    assert merge_results([("a", a), ("b", refrozen | {"frozen": a["frozen"]})])["film"] == "mlp"
    summed = _results([1], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}}, rec_reduction="sum")
    assert a["rec_reduction"] == "mean" and summed["rec_reduction"] == "sum"
    with pytest.raises(ValueError, match="b: PDP's L_rec reduction is 'sum' but a has 'mean'"):
        merge_results([("a", a), ("b", summed)])
    older = {k: v for k, v in refrozen.items() if k != "rec_reduction"} | {"frozen": a["frozen"]}
    assert merge_results([("a", a), ("older", older)])["rec_reduction"] == "mean"  # every older run: the mean
    # a file from before per-method seeds whose method finished fewer seeds than the table's
    old = _results([1, 2], {"pdp": {1: [1.0, 1.0, 1.0, 1.0]}})
    del old["methods"]["pdp"]["seeds"]
    with pytest.raises(ValueError, match=r"old: pdp scene0 has 1 per-seed values for seeds \[1, 2\]"):
        merge_results([("a", a), ("old", old)])


def test_merge_results_cli_writes_both_files_and_never_overwrites_an_input(tmp_path, capsys):
    from lerobot_pdp.cli import main

    for seed in (0, 1):
        d = tmp_path / f"seed{seed}"
        d.mkdir()
        (d / "results.json").write_text(json.dumps(_results([seed], {"pdp": {seed: [1.0, 0.5, 1.0, 1.0]}})))
    assert main(["merge-results", str(tmp_path / "seed0"), str(tmp_path / "seed1" / "results.json"),
                 "--out", str(tmp_path / "all")]) == 0
    res = json.loads((tmp_path / "all" / "results.json").read_text())
    assert res["methods"]["pdp"]["scene1"]["success"] == [0.5, 0.5]
    assert res["merged_from"] == ["../seed0/results.json", "../seed1/results.json"]  # movable with its parts
    assert "| pdp | 100.0 ± 0.0 | 50.0 ± 0.0 |" in (tmp_path / "all" / "results.md").read_text()
    assert sorted(p.name for p in (tmp_path / "all").iterdir()) == ["results.json", "results.md"]
    capsys.readouterr()
    assert main(["merge-results", str(tmp_path / "seed0"), str(tmp_path / "seed1"), "--out", str(tmp_path / "seed1")]) == 2
    assert "would overwrite one of the inputs" in capsys.readouterr().err
    assert main(["merge-results", str(tmp_path / "seed0"), str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2
    assert "no results file at" in capsys.readouterr().err and not (tmp_path / "x").exists()
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "other.json").write_text(json.dumps({"env": "reach-around"}))
    (tmp_path / "fig.png").write_bytes(b"\x89PNG\r\n\x1a\n")  # not even text
    for bad, msg in (("bad.json", "bad.json is not JSON"), ("fig.png", "fig.png is not JSON"), ("other.json", "other.json: not a benchmark results.json")):
        assert main(["merge-results", str(tmp_path / "seed0"), str(tmp_path / bad), "--out", str(tmp_path / "x")]) == 2
        assert msg in capsys.readouterr().err and not (tmp_path / "x").exists()


@pytest.mark.parametrize(("argv", "expected"), [
    ([], ([0, 1, 2], 40, ["pdp", "dp", "bc"])),
    (["--quick"], ([0], 20, ["pdp", "dp"])),
    (["--quick", "--seeds", "1", "2", "--rollouts", "4", "--methods", "bc"], ([1, 2], 4, ["bc"])),
    (["--seeds", "0", "--rollouts=8"], ([0], 8, ["pdp", "dp", "bc"])),
])
def test_quick_changes_only_the_defaults_of_the_benchmark_command(argv, expected):
    """The same from Python (``main([...])``) as from the shell: nothing is read from ``sys.argv``."""
    from lerobot_pdp.cli import benchmark_config, build_parser

    cfg = benchmark_config(build_parser().parse_args(["benchmark", "--env", "reach-around", "--out", "o", *argv]))
    assert (cfg.seeds, cfg.rollouts, cfg.methods) == expected
    assert cfg.quick == ("--quick" in argv) and cfg.film is None  # None: the env's FiLM form
    film = benchmark_config(build_parser().parse_args(["benchmark", "--env", "avoiding", "--out", "o", "--film",
                                                       "affine", *argv]))
    assert film.film == "affine" and (film.seeds, film.rollouts, film.methods) == expected
    assert cfg.rec_reduction == "mean" and benchmark_config(build_parser().parse_args(
        ["benchmark", "--env", "avoiding", "--out", "o", "--rec-reduction", "sum", *argv])).rec_reduction == "sum"


def test_rollout_figures_split_main_methods_from_ablations_whatever_was_asked(tmp_path, monkeypatch):
    """`--methods pdp_onehot pdp dp` (ablations named explicitly, no --ablations) still draws the ablations in
    their own grid, headed by PDP, and keeps them out of the main methods' grids."""
    from lerobot_pdp.benchmark import figures

    drawn: dict[str, list[str]] = {}
    monkeypatch.setattr(figures, "rollouts_grid",
                        lambda suite, traces, scenes, png, plane: drawn.setdefault(png.name, list(traces)) and png)
    monkeypatch.setattr(figures, "interpolation_sweep", lambda *a, **k: None)
    names = ["pdp_onehot", "pdp", "dp"]
    for m in names:
        (tmp_path / "runs" / m / "seed0").mkdir(parents=True)
        (tmp_path / "runs" / m / "seed0" / "traces.json").write_text(json.dumps({"0": []}))
    cfg = BenchmarkConfig(env="reach-around", out=tmp_path, seeds=[0], methods=names)
    figures.write_figures(get_suite_env("reach-around"), tmp_path, cfg, {(m, 0): tmp_path for m in names}, None)
    assert drawn == {"rollouts_xy.png": ["pdp", "dp"], "rollouts_yz.png": ["pdp", "dp"],
                     "rollouts_ablations.png": ["pdp", "pdp_onehot"]}


def test_atomic_write_replaces_whole_files_and_leaves_no_temp_file_when_it_fails(tmp_path):
    from lerobot_pdp.atomic import write_text_atomic

    target = tmp_path / "results.json"
    write_text_atomic(target, "old")
    write_text_atomic(target, "new")
    assert target.read_text() == "new"
    (tmp_path / "busy").mkdir()  # the rename onto a directory fails: the error surfaces, no temp file stays
    with pytest.raises(OSError):
        write_text_atomic(tmp_path / "busy", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy", "results.json"]


def test_a_staged_folder_moved_into_place_has_a_plain_folders_permissions(tmp_path):
    """Adapted and taught checkpoints are staged folders renamed into place: readable by whoever may read a
    folder made by mkdir (mkdtemp's own 0700 would lock out a robot service running as another user)."""
    import os

    from lerobot_pdp.atomic import staging_dir

    old = os.umask(0o022)
    try:
        with staging_dir(tmp_path / "ckpt") as tmp:
            (tmp / "config.json").write_text("{}")
            os.replace(tmp, tmp_path / "ckpt")
    finally:
        os.umask(old)
    assert (tmp_path / "ckpt").stat().st_mode & 0o777 == 0o755
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]


def test_a_writer_killed_while_staging_leaves_nothing_once_the_next_one_writes(tmp_path):
    """A process killed inside a staging folder (SIGKILL: its cleanup never runs) leaves it behind, e.g. inside a
    lerobot-train checkpoint folder; the next writer of that place sweeps it, and only the dead writer's."""
    import signal
    import subprocess
    import sys

    from lerobot_pdp.atomic import staging_dir

    code = ("import sys, time\nfrom lerobot_pdp.atomic import staging_dir\n"
            "with staging_dir(sys.argv[1], prefix='.pdp-save-') as tmp:\n"
            "    (tmp / 'config.json').write_text('{}')\n    print('staged', flush=True)\n    time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "pretrained_model")], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "staged"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (left,) = tmp_path.glob(".pdp-save-*")
    other_host = tmp_path / ".pdp-save-elsewhere-1-x"  # a shared file system's other machine: not ours to judge
    other_host.mkdir()
    with staging_dir(tmp_path / "pretrained_model", prefix=".pdp-save-") as tmp:
        assert not left.exists() and other_host.exists()
        with staging_dir(tmp_path / "pretrained_model", prefix=".pdp-save-"):  # a live writer's stays
            assert tmp.exists()


@pytest.mark.parametrize(("device", "message"), [("gpu", "is not a torch device"), ("cuda:0", "no CUDA device")])
def test_benchmark_refuses_a_bad_device_before_any_work(tmp_path, capsys, device, message):
    import torch

    from lerobot_pdp.cli import main

    if device.startswith("cuda") and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert main(["benchmark", "--env", "reach-around", "--out", str(tmp_path / "b"), "--device", device]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "b").exists()


def test_merge_results_merges_validation_records_of_one_method_per_folder(tmp_path, capsys):
    """Validation runs made one method per folder merge into one results.json and one validation.json (what
    settings.VALIDATION_RECORDS names); a method validated twice is refused."""
    from lerobot_pdp.cli import main

    scenes = (0, "val1", "val2", "val3", "val4")
    for method, rates in (("pdp", [1.0, 1.0, 0.9, 0.0, 0.0]), ("dp", [1.0, 0.5, 0.5, 0.0, 0.0])):
        d = tmp_path / method
        d.mkdir()
        cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[100], split="validation", scenes=scenes)
        run = {"scenes": {str(sc): {"success": r, "collision": 0.0} for sc, r in zip(scenes, rates, strict=True)}}
        res = aggregate("reach-around", cfg, {method: {100: run}}, {}, TrainSettings(steps=10), 10)
        (d / "results.json").write_text(json.dumps(res))
        rec = {"env": "reach-around", "split": "validation", "rollouts": 40, "sampler_candidates": [[20, "leading"]],
               "adapt_candidates": {"noise": [{}]},
               "methods": {method: {"seeds": [100], "scenes": list(map(str, scenes)), "sampler": [], "adapt": [],
                                    "chosen": {"sampler": [20, "leading"], "adapt": {}}}}}
        (d / "validation.json").write_text(json.dumps(rec))
    assert main(["merge-results", str(tmp_path / "pdp"), str(tmp_path / "dp"), "--out", str(tmp_path / "all")]) == 0
    merged = json.loads((tmp_path / "all" / "validation.json").read_text())
    assert list(merged["methods"]) == ["pdp", "dp"] and merged["env"] == "reach-around"
    assert "## dp (seeds 100)" in (tmp_path / "all" / "validation.md").read_text()
    assert set(json.loads((tmp_path / "all" / "results.json").read_text())["methods"]) == {"pdp", "dp"}
    capsys.readouterr()
    other = json.loads((tmp_path / "dp" / "validation.json").read_text())
    (tmp_path / "dp" / "validation.json").write_text(json.dumps({**other, "rollouts": 20}))
    assert main(["merge-results", str(tmp_path / "pdp"), str(tmp_path / "dp"), "--out", str(tmp_path / "x")]) == 2
    assert "rollouts is 20" in capsys.readouterr().err and not (tmp_path / "x").exists()
    (tmp_path / "dp" / "validation.json").unlink()  # a run without --validate: said, not merged
    assert main(["merge-results", str(tmp_path / "pdp"), str(tmp_path / "dp"), "--out", str(tmp_path / "y")]) == 0
    assert "validation records not merged: no" in capsys.readouterr().out
    assert not (tmp_path / "y" / "validation.json").exists() and (tmp_path / "y" / "results.json").is_file()


def test_merging_validation_records_compares_only_the_candidate_lists_their_methods_used():
    """A PDP record validated after PDP's list changed merges with a DP record made before (DP's own list is
    the same in both); two records whose PDP-like methods used different fit lists, or that observed different
    things (a camera record beside a state one), are refused by name."""
    from lerobot_pdp.benchmark.validation import merge_validation_records

    def record(methods, fit, noise=({},)):
        rows = {"seeds": [100], "scenes": ["0", "val1"], "sampler": [], "adapt": [],
                "chosen": {"sampler": [20, "leading"], "adapt": {}}}
        return {"env": "reach-around", "split": "validation", "rollouts": 40, "sampler_candidates": [[20, "leading"]],
                "adapt_candidates": {"fit_latent": list(fit), "noise": list(noise), "finetune": [{}]},
                "methods": {m: rows for m in methods}}

    new_pdp = record(["pdp"], [{}, {"noise": "chunks"}], noise=[{}, {"per_chunk": True}])
    old_dp_bc = record(["dp", "bc"], [{}, {"steps": 10}], noise=[{}, {"per_chunk": True}])
    merged = merge_validation_records([("new/validation.json", new_pdp), ("old/validation.json", old_dp_bc)])
    assert list(merged["methods"]) == ["pdp", "dp", "bc"]
    assert merged["adapt_candidates"]["fit_latent"] == [{}, {"noise": "chunks"}]  # the list PDP was validated with
    # DP's list differs between the two records, and only the DP record holds a method that used it
    merged = merge_validation_records([("new/validation.json", record(["pdp"], [{}], noise=[{"x": 1}])),
                                       ("old/validation.json", old_dp_bc)])
    assert merged["adapt_candidates"]["noise"] == [{}, {"per_chunk": True}]
    with pytest.raises(ValueError, match=r"old/validation.json: adapt_candidates\['fit_latent'\] \(validated for "
                                         r"pdp_concat\)"):
        merge_validation_records([("new/validation.json", new_pdp), ("old/validation.json",
                                                                      record(["pdp_concat"], [{}, {"steps": 10}]))])
    with pytest.raises(ValueError, match="'act' is not a benchmark method of reach-around"):
        merge_validation_records([("new/validation.json", record(["act"], [{}]))])
    with pytest.raises(ValueError, match="already validated in another input"):
        merge_validation_records([("a/validation.json", new_pdp), ("b/validation.json", new_pdp)])
    camera = {**old_dp_bc, "observation": {"obs": "images", "camera": "oblique", "image_size": 64}}
    with pytest.raises(ValueError, match=r"camera/validation.json: observation is \{'obs': 'images'.* but "
                                         r"new/validation.json has None"):  # a camera record beside a state one
        merge_validation_records([("new/validation.json", new_pdp), ("camera/validation.json", camera)])
    merged = merge_validation_records([("camera/validation.json", camera),
                                       ("pdp/validation.json", {**new_pdp, "observation": camera["observation"]})])
    assert merged["observation"] == camera["observation"]


def _taught(method: str, seed: int, new_route: float, **protocol) -> dict:
    """A --teach record as benchmark.teaching writes it: one (method, seed) taught one frozen setting."""
    scene0 = {"success": 1.0, "collision": 0.0, "n": 8, "coverage": 1.0}
    run = {"scene": "4", "steps": 300, "lr": 1e-4, "new_route": {"success": new_route, "collision": 0.0, "n": 4},
           "scene0": scene0, "teach_seconds": 12.0}
    return {"env": "reach-around", "split": "test", "rollouts": 4, "rollouts_scene0": 8, "batch_size": 64,
            "demo_share": 0.25, **protocol,
            "runs": {method: {str(seed): {"method": method, "seed": seed, "rollouts": 4, "base_scene0": scene0,
                                          "runs": {"4 steps=300 lr=0.0001": run}, "chosen": "steps=300 lr=0.0001"}}}}


def test_merge_results_merges_the_teaching_records_of_runs_made_method_by_method(tmp_path, capsys):
    """BC and DP taught by two benchmark runs side by side: merge-results writes one teach.json / teach.md beside
    the merged table, and refuses a (method, seed) taught twice or another teaching protocol, naming the run."""
    from lerobot_pdp.benchmark.results import merge_results
    from lerobot_pdp.cli import main

    for method, rate in (("bc", 0.0), ("dp", 0.75)):
        d = tmp_path / method
        d.mkdir()
        res = _results([6], {method: {6: [1.0, 0.5, 1.0, 1.0]}}) | {"teach": _taught(method, 6, rate)}
        (d / "results.json").write_text(json.dumps(res))
    assert main(["merge-results", str(tmp_path / "bc"), str(tmp_path / "dp"), "--out", str(tmp_path / "all")]) == 0
    teach = json.loads((tmp_path / "all" / "teach.json").read_text())
    assert sorted(teach["runs"]) == ["bc", "dp"] and teach["rollouts_scene0"] == 8
    assert teach == json.loads((tmp_path / "all" / "results.json").read_text())["teach"]
    md = (tmp_path / "all" / "teach.md").read_text()
    assert "| bc | 6 | 4 | 300 | 0.0001 | - | 0.0% | 100.0% (100.0%) |" in md
    assert "| dp | 6 | 4 | 300 | 0.0001 | - | 75.0% | 100.0% (100.0%) |" in md
    assert "teaching record" in capsys.readouterr().out
    # merged again into the same folder from runs without teaching: the earlier teaching record goes
    for method in ("bc", "dp"):
        (tmp_path / f"plain_{method}").mkdir()
        (tmp_path / f"plain_{method}" / "results.json").write_text(json.dumps(_results([6], {method: {6: [1.0] * 4}})))
    assert main(["merge-results", str(tmp_path / "plain_bc"), str(tmp_path / "plain_dp"), "--out",
                 str(tmp_path / "all")]) == 0
    assert not (tmp_path / "all" / "teach.json").exists() and not (tmp_path / "all" / "teach.md").exists()
    assert "removed" in capsys.readouterr().out
    one = _results([6], {"bc": {6: [1.0] * 4}})
    again = _results([7], {"dp": {7: [1.0] * 4}})
    with pytest.raises(ValueError, match="bc seed 6 is taught in two of the merged runs"):
        merge_results([("a", one | {"teach": _taught("bc", 6, 0.0)}), ("b", again | {"teach": _taught("bc", 6, 0.0)})])
    with pytest.raises(ValueError, match="b: teaching demo_share is 0.5 but a has 0.25"):
        merge_results([("a", one | {"teach": _taught("bc", 6, 0.0)}),
                       ("b", again | {"teach": _taught("dp", 7, 0.0, demo_share=0.5)})])
    with pytest.raises(ValueError, match="b: teaching budget is 'quick' but a has None"):  # a key only one has
        merge_results([("a", one | {"teach": _taught("bc", 6, 0.0)}),
                       ("b", again | {"teach": _taught("dp", 7, 0.0, budget="quick")})])


def test_merge_results_refuses_a_benchmark_folder_as_out_and_scene_lists_that_differ(tmp_path, capsys):
    """--out a benchmark run's own folder would replace its results and records: refused, untouched. Runs whose
    methods cover other scenes make no one table: refused naming both, nothing written. Adaptation settings
    besides the defaults survive the merge."""
    from lerobot_pdp.cli import main

    a = _results([0], {"pdp": {0: [1.0, 0.5, 1.0, 1.0]}})
    a["methods"]["pdp"]["adapt"] = {"noise": "chunks"}
    b = _results([1], {"pdp": {1: [1.0, 1.0, 0.0, 1.0]}})
    b["methods"]["pdp"]["adapt"] = {"noise": "chunks"}
    for name, res in (("a", a), ("b", b)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(res))
    run = tmp_path / "run"
    (run / "runs").mkdir(parents=True)
    (run / "results.json").write_text(json.dumps(a))
    (run / "teach.json").write_text("{}")
    assert main(["merge-results", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(run)]) == 2
    assert "holds a benchmark run" in capsys.readouterr().err
    assert json.loads((run / "results.json").read_text()) == a and (run / "teach.json").is_file()
    assert main(["merge-results", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(run / "figures")]) == 2
    assert f"lies inside the benchmark run {run.resolve()}" in capsys.readouterr().err
    assert not (run / "figures").exists()
    assert main(["merge-results", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "m")]) == 0
    merged = json.loads((tmp_path / "m" / "results.json").read_text())
    assert merged["methods"]["pdp"]["adapt"] == {"noise": "chunks"}
    assert "pdp {'noise': 'chunks'}" in (tmp_path / "m" / "results.md").read_text()
    # an earlier merge is a fine --out: merged again in place
    assert main(["merge-results", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "m")]) == 0
    capsys.readouterr()
    c = _results([2], {"dp": {2: [1.0, 1.0, 1.0]}}, scenes=(0, 1, 2))
    (tmp_path / "c.json").write_text(json.dumps(c))
    assert main(["merge-results", str(tmp_path / "a"), str(tmp_path / "c.json"), "--out", str(tmp_path / "ac")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'c.json'}: dp has scenes ['scene0', 'scene1', 'scene2']" in err and "pdp has" in err, err
    assert not (tmp_path / "ac").exists()


def test_a_benchmark_into_another_envs_run_folder_is_refused_before_writing(tmp_path):
    """--out of a reach-around run given to an avoiding benchmark: refused at once, naming the run's env, before
    the avoiding dataset is generated into that run's data folder."""
    from lerobot_pdp.benchmark.protocol import run_benchmark

    (tmp_path / "results.json").write_text(json.dumps({"env": "reach-around"}))
    cfg = BenchmarkConfig(env="avoiding", out=tmp_path, seeds=[100], split="validation", scenes=[0, "val1"])
    with pytest.raises(ValueError, match=f"{tmp_path} is a benchmark run of reach-around, not avoiding: give --env "
                                         "reach-around"):
        run_benchmark(cfg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]
