"""results.json / results.md aggregation over seeds (pure functions; the protocol tests run the real thing)."""

import json
from pathlib import Path

import pytest

from lerobot_pdp.benchmark.protocol import (
    BenchmarkConfig,
    TrainSettings,
    aggregate,
    ensure_dataset,
    results_markdown,
)
from lerobot_pdp.envs import get_suite_env


def _run(rates: list[float]) -> dict:
    return {"scenes": {str(s): {"success": r, "collision": 0.0} for s, r in enumerate(rates)}}


def test_mean_and_std_over_seeds_in_json_and_table():
    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0, 1])
    per_run = {"pdp": {0: _run([1.0, 0.9, 1.0, 0.8]), 1: _run([1.0, 0.7, 1.0, 1.0])},
               "dp": {0: _run([0.5, 0.0, 1.0, 0.0])}}  # a method with one finished seed so far
    init = {0: {"encoder@0": 0.5, "random@0": 0.0}, 1: {"encoder@0": 0.7, "random@0": 0.1}}
    res = aggregate("reach-around", cfg, per_run, init, TrainSettings(steps=10), 10)
    s1 = res["methods"]["pdp"]["scene1"]
    assert s1["success"] == [0.9, 0.7] and s1["mean"] == pytest.approx(0.8) and s1["std"] == pytest.approx(0.1)
    assert res["methods"]["pdp"]["shifted_avg"] == pytest.approx((0.8 + 1.0 + 0.9) / 3)
    assert res["methods"]["dp"]["scene0"]["success"] == [0.5]
    assert res["init_ablation"]["encoder@0"]["mean"] == pytest.approx(0.6)
    md = results_markdown(res)
    assert "| pdp | 100.0 ± 0.0 | 80.0 ± 10.0 | 100.0 ± 0.0 | 90.0 ± 10.0 | 90.0 |" in md
    assert "| dp | 50.0 | 0.0 | 100.0 | 0.0 |" in md  # one seed: no std
    assert "| warm (encoder) | 60.0 ± 10.0 |" in md and "| random | 5.0 ± 5.0 |" in md


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
