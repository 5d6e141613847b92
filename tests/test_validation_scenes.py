"""The validation split: shipped validation scenes are what their descriptions say (checked with the scripted
experts, no policy), and ``benchmark --split validation`` evaluates them on validation seeds, never mixed with
the test scenes 1-3 or the test seeds."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import lerobot_pdp.envs  # noqa: F401  (registers the suite and the gym ids)
from lerobot_pdp.benchmark.data import demo_root, ensure_demo, feasible_training_modes
from lerobot_pdp.benchmark.results import aggregate, merge_results, results_markdown
from lerobot_pdp.benchmark.settings import (
    SCENES,
    TEACH_SCENES,
    TEST_SEEDS,
    VALIDATION_SCENES,
    VALIDATION_SEEDS,
    BenchmarkConfig,
    TrainSettings,
    check_split,
    scene_label,
    scene_seed_offset,
    split_scenes,
    split_seeds,
)
from lerobot_pdp.cli import benchmark_config, build_parser
from lerobot_pdp.envs.recording import run_expert_episode
from lerobot_pdp.envs.scene import SceneError, load_scene, shipped_scene_path, validation_scene_names
from lerobot_pdp.envs.suite import NOVEL, get_suite_env

# What each scene's description promises: its only feasible training mode, or None (no training mode open;
# the scene ships the way-points of a new route).
EXPECTED: dict[str, dict[str, int | None]] = {
    "reach-around": {"val1": 4, "val2": 7, "val3": None, "val4": None},  # right-tight, under-wide
    "avoiding": {"val1": 13, "val2": 8, "val3": None, "val4": None, "val5": None},  # R-L-2, L-R-1
    "pick-place": {"val1": 46, "val2": 17, "val3": None, "val4": None, "val5": None, "val6": None, "val7": None},
    "kitchen-microwave": {"val1": 0, "val2": 4, "val3": None},  # front, high-right
}
CASES = [(env, name) for env, scenes in EXPECTED.items() for name in scenes]


def test_expectations_cover_every_shipped_validation_scene():
    assert set(EXPECTED) == set(VALIDATION_SCENES)
    for env, names in VALIDATION_SCENES.items():
        assert list(names) == validation_scene_names(get_suite_env(env).scene_key) == list(EXPECTED[env])
        # the split's families: at least two scenes with one training mode open, two with none (the kitchen,
        # whose arm sweeps a large volume, has one scene with none so far)
        modes = list(EXPECTED[env].values())
        assert sum(m is None for m in modes) >= (1 if env == "kitchen-microwave" else 2)
        assert sum(m is not None for m in modes) >= 2


@pytest.mark.parametrize(("env", "name"), CASES)
def test_validation_scene_loads_and_resets_collision_free(env: str, name: str):
    suite = get_suite_env(env)
    path = shipped_scene_path(suite.scene_key, name)
    assert path.is_file() and path.name == f"{suite.scene_key}_{name}.json"
    sc = load_scene(name, suite.scene_key)
    assert f"val {name[3:]}:" in sc.name and sc.description.startswith("Validation scene.")
    assert (sc.waypoints is not None) == (EXPECTED[env][name] is None)
    e = gym.make(suite.gym_id, scene=name, disable_env_checker=True)
    try:
        e.reset(seed=0)
        for _ in range(5):  # standing still at the reset pose touches nothing
            _, _, terminated, _, info = e.step(np.zeros(e.action_space.shape, dtype=np.float32))
            assert not info["collided"] and not terminated
    finally:
        e.close()


@pytest.mark.parametrize(("env", "name"), CASES)
def test_exactly_the_described_training_modes_are_feasible(env: str, name: str):
    suite = get_suite_env(env)
    open_mode = EXPECTED[env][name]
    assert feasible_training_modes(suite, name) == ([] if open_mode is None else [open_mode])
    if open_mode is not None:  # the open mode's demonstrations succeed for other jitter too
        for seed in (11, 12):
            info, states, _ = run_expert_episode(suite, name, mode=open_mode, seed=seed)
            assert info["is_success"] and not info["collided"]
            assert suite.classify_mode(states) == open_mode


@pytest.mark.parametrize(("env", "name"), [c for c in CASES if EXPECTED[c[0]][c[1]] is None])
def test_waypoint_demonstration_succeeds_on_a_new_route(env: str, name: str):
    suite = get_suite_env(env)
    sc = load_scene(name, suite.scene_key)
    for seed in (0, 1, 2):
        info, states, _ = run_expert_episode(suite, name, waypoints=sc.waypoints, seed=seed)
        assert info["is_success"] and not info["collided"]
        assert suite.classify_mode(states) == NOVEL  # a route no training mode takes


@pytest.mark.parametrize("env", sorted(VALIDATION_SCENES))
def test_new_routes_differ_from_scene_3(env: str):
    """The zero-mode validation scenes' routes are not scene 3's: their way-points lie elsewhere."""
    suite = get_suite_env(env)
    s3 = np.asarray(load_scene(3, suite.scene_key).waypoints)
    for name, mode in EXPECTED[env].items():
        if mode is None:
            wps = np.asarray(load_scene(name, suite.scene_key).waypoints)
            far = [np.min(np.linalg.norm(s3 - w, axis=1)) > 0.05 for w in wps]
            assert any(far), f"{env} {name}: every way-point lies on scene 3's route"


TEACH_CASES = [(env, scene) for env, splits in TEACH_SCENES.items() for scenes in splits.values() for scene in scenes]


@pytest.mark.parametrize(("env", "scene"), TEACH_CASES)
def test_teaching_scenes_open_no_training_mode_and_ship_a_new_route(env: str, scene: int | str):
    """``--teach``'s zero-mode scenes: every training mode's expert fails there, the shipped way-points succeed on
    a route no training mode takes; a test one is outside the test split's adaptation scenes and has its own
    seeds and name."""
    suite = get_suite_env(env)
    sc = load_scene(scene, suite.scene_key)
    assert feasible_training_modes(suite, scene) == []
    for seed in (0, 1, 2):
        info, states, _ = run_expert_episode(suite, scene, waypoints=sc.waypoints, seed=seed)
        assert info["is_success"] and not info["collided"]
        assert suite.classify_mode(states) == NOVEL
    if not isinstance(scene, str):
        assert scene not in SCENES and sc.description.startswith("Zero-mode test scene.")
        others = [*SCENES, *VALIDATION_SCENES[env]]
        assert scene_seed_offset(scene) not in {scene_seed_offset(s) for s in others}
        assert sc.name not in {load_scene(s, suite.scene_key).name for s in others}
    else:
        assert scene in VALIDATION_SCENES[env]


def test_validation_names_never_collide_with_test_scenes():
    for env in VALIDATION_SCENES:
        key = get_suite_env(env).scene_key
        test_names = {load_scene(k, key).name for k in SCENES}
        val = [load_scene(n, key) for n in VALIDATION_SCENES[env]]
        assert not test_names & {sc.name for sc in val}
        assert len({sc.name for sc in val}) == len(val)
        labels = [scene_label(s) for s in (*SCENES, *VALIDATION_SCENES[env])]
        offsets = [scene_seed_offset(s) for s in (*SCENES, *VALIDATION_SCENES[env])]
        assert len(set(labels)) == len(labels) and len(set(offsets)) == len(offsets)
    assert not set(VALIDATION_SEEDS) & set(TEST_SEEDS)
    with pytest.raises(SceneError, match="ships no validation scene 'val9'"):
        load_scene("val9", "reach_around")


def _args(*extra: str):
    return build_parser().parse_args(["benchmark", "--env", "avoiding", "--out", "unused", *extra])


def test_split_flag_sets_scenes_and_seeds():
    test = benchmark_config(_args())
    assert (test.split, test.scenes, test.seeds) == ("test", SCENES, [0, 1, 2])  # as before the split existed
    val = benchmark_config(_args("--split", "validation"))
    assert val.split == "validation" and val.scenes == (0, "val1", "val2", "val3", "val4", "val5") == split_scenes(
        "avoiding", "validation")
    assert val.seeds == list(VALIDATION_SEEDS) == split_seeds("validation")
    assert benchmark_config(_args("--split", "validation", "--quick")).seeds == [VALIDATION_SEEDS[0]]
    picked = benchmark_config(_args("--split", "validation", "--scenes", "0", "val3", "--seeds", "101"))
    assert picked.scenes == (0, "val3") and picked.seeds == [101]
    cam = benchmark_config(_args("--split", "validation", "--obs", "images"))
    assert cam.obs == "images" and cam.split == "validation" and cam.methods == ["pdp", "dp", "vqbet"]
    with pytest.raises(ValueError, match="ships no validation scenes"):
        split_scenes("no-such-env", "validation")


def test_mixing_the_splits_is_refused_before_anything_runs(tmp_path):
    check_split("validation", (0, "val1"), [100])
    check_split("test", (0, 1, 2, 3), [0, 1, 2])
    for split, scenes, seeds in [("validation", (0, 1), [100]), ("validation", (0, "val1"), [0]),
                                 ("test", (0, "val1"), [0]), ("test", (0, 1), [100]), ("dev", (0,), [0])]:
        with pytest.raises(ValueError):
            check_split(split, scenes, seeds)
    from lerobot_pdp.benchmark.protocol import run_benchmark

    cfg = BenchmarkConfig(env="avoiding", out=tmp_path / "bench", seeds=[0], scenes=(0, "val1"), split="validation")
    with pytest.raises(ValueError, match="test seed"):
        run_benchmark(cfg)
    assert not (tmp_path / "bench").exists()


def test_validation_demo_is_the_scene_waypoints(tmp_path):
    suite = get_suite_env("reach-around")
    root, source = ensure_demo(suite, tmp_path, "val3")
    assert root == demo_root(suite, tmp_path, "val3") and root.name == "reach_around_scene_val3_demo"
    assert source == "scene way-points (new route)"
    assert json.loads((root / "meta" / "info.json").read_text())["total_episodes"] == 1


def _run(scenes: tuple, rates: list[float]) -> dict:
    return {"scenes": {str(s): {"success": r, "collision": 0.0} for s, r in zip(scenes, rates, strict=True)}}


def test_results_record_the_split_and_its_scenes():
    scenes = split_scenes("reach-around", "validation")
    cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[100], scenes=scenes, split="validation")
    res = aggregate("reach-around", cfg, {"pdp": {100: _run(scenes, [1.0, 0.5, 1.0, 0.0, 0.5])}}, {},
                    TrainSettings(steps=10), 10)
    assert res["split"] == "validation" and res["scenes"] == [0, "val1", "val2", "val3", "val4"]
    entry = res["methods"]["pdp"]
    assert [k for k in entry if k.startswith("scene")] == ["scene0", "scene_val1", "scene_val2", "scene_val3",
                                                          "scene_val4"]
    assert entry["shifted_avg"] == pytest.approx(0.5)
    md = results_markdown(res)
    assert "(validation split)" in md and "| Validation val1 | Validation val2 |" in md
    test_cfg = BenchmarkConfig(env="reach-around", out=Path("unused"), seeds=[0])
    test = aggregate("reach-around", test_cfg, {"pdp": {0: _run(SCENES, [1.0] * 4)}}, {}, TrainSettings(steps=10), 10)
    assert test["split"] == "test" and test["scenes"] == [0, 1, 2, 3] and "scene1" in test["methods"]["pdp"]
    with pytest.raises(ValueError, match="never merged"):
        merge_results([("a", test), ("b", {**res, "train": test["train"]})])


def test_make_dataset_and_plot_by_validation_scene_name(tmp_path):
    """``make-dataset --scene val1`` records the name (not a path in the working directory), so
    ``plot-dataset`` finds the scene again."""
    from lerobot_pdp.cli import main
    from lerobot_pdp.envs.recording import read_dataset_meta

    out = tmp_path / "ds"
    assert main(["make-dataset", "--env", "avoiding", "--scene", "val1", "--modes", "13", "--episodes-per-mode", "1",
                 "--out", str(out), "--no-progress"]) == 0
    assert read_dataset_meta(out)["scene"] == "val1"
    assert main(["plot-dataset", str(out), "--out", str(tmp_path / "ds.png")]) == 0
    assert (tmp_path / "ds.png").is_file()


def test_lerobot_eval_env_config_takes_a_validation_scene():
    """``lerobot-eval --env.scene=val3`` builds the validation scene."""
    from lerobot.envs.factory import make_env_config

    cfg = make_env_config("pdp_avoiding", scene="val3")
    assert cfg.scene == "val3" and cfg.gym_kwargs["scene"] == "val3"
    e = gym.make(get_suite_env("avoiding").gym_id, **cfg.gym_kwargs)
    assert "post_r2_0" not in {b.name for b in e.unwrapped.obstacles}
    e.close()
