"""Dataset generation (LeRobotDataset v3 with mode task strings), plotting and the lerobot-pdp CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import lerobot_pdp.envs as envs
from lerobot_pdp.cli import main as cli_main
from lerobot_pdp.envs.recording import DemoGenerationError, make_dataset, read_dataset_meta


def _data_table(root: Path):
    files = sorted((root / "data").glob("*/*.parquet"))
    return pq.read_table(files[0]).replace_schema_metadata(None)


@pytest.fixture(scope="module")
def reach_dataset(tmp_path_factory) -> Path:
    return make_dataset("reach-around", tmp_path_factory.mktemp("ds") / "reach", episodes_per_mode=2, seed=0,
                        progress=False)


def test_dataset_loads_with_lerobot_and_carries_mode_tasks(reach_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/reach", root=reach_dataset)
    suite = envs.get_suite_env("reach-around")
    assert ds.num_episodes == 16 and ds.fps == 50
    assert set(ds.meta.tasks.index) == {suite.task_string(m) for m in range(8)}
    assert ds.features["observation.state"]["shape"] == (6,)
    assert ds.features["observation.environment_state"]["shape"] == (6,)
    assert ds.features["action"]["shape"] == (3,)
    assert ds.features["observation.state"]["names"][:3] == ["ee_x", "ee_y", "ee_z"]
    meta = read_dataset_meta(reach_dataset)
    assert meta["env"] == "reach-around" and meta["scene"] == 0 and meta["episode_modes"] == [
        m for m in range(8) for _ in range(2)]
    # each accepted episode's closest approach to an obstacle: positive, the expert's margin
    assert len(meta["episode_min_clearance"]) == 16 and all(0 < c < 0.3 for c in meta["episode_min_clearance"])
    # each episode's task string matches what the classifier says about its states
    for ep in range(ds.num_episodes):
        lo = int(ds.meta.episodes["dataset_from_index"][ep])
        hi = int(ds.meta.episodes["dataset_to_index"][ep])
        frames = [ds[i] for i in range(lo, hi)]
        states = np.stack([f["observation.state"].numpy() for f in frames])
        assert envs.parse_task_mode(frames[0]["task"]) == suite.classify_mode(states) == ep // 2
        assert np.abs(np.stack([f["action"].numpy() for f in frames])).max() <= 1.0


def test_same_seed_same_dataset_other_seed_differs(reach_dataset, tmp_path):
    again = make_dataset("reach-around", tmp_path / "again", episodes_per_mode=2, seed=0, progress=False)
    assert _data_table(again).equals(_data_table(reach_dataset))
    other = make_dataset("reach-around", tmp_path / "other", modes=[0, 1], episodes_per_mode=2, seed=1,
                         progress=False)
    assert not _data_table(other).equals(_data_table(again).slice(0, _data_table(other).num_rows))


def test_refuses_existing_output(reach_dataset):
    before = sorted(p.name for p in reach_dataset.rglob("*"))
    with pytest.raises(FileExistsError, match="already exists"):
        make_dataset("reach-around", reach_dataset, episodes_per_mode=1, progress=False)
    assert sorted(p.name for p in reach_dataset.rglob("*")) == before


def test_infeasible_mode_fails_cleanly(tmp_path):
    out = tmp_path / "sub" / "bad"
    with pytest.raises(DemoGenerationError, match=r"mode 2 \(left-tight\).*3 attempts"):
        make_dataset("reach-around", out, scene=1, modes=["left-tight"], episodes_per_mode=1, max_attempts=3,
                     progress=False)
    assert not out.exists()
    assert list((tmp_path / "sub").iterdir()) == []  # no half-written temp dir left behind


def test_waypoint_demos_in_scene3_are_labelled_novel(tmp_path):
    out = make_dataset("avoiding", tmp_path / "av3", scene=3, waypoints="scene", episodes_per_mode=2,
                       progress=False)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/av3", root=out)
    assert ds.num_episodes == 2 and list(ds.meta.tasks.index) == ["mode novel: novel"]
    assert read_dataset_meta(out)["waypoints"][0] == [0.525, -0.28]


def test_waypoints_from_file_and_argument_errors(tmp_path):
    wp = tmp_path / "route.json"
    wp.write_text(json.dumps([[0.0, -0.3, 0.4], [0.19, -0.12, 0.59], [0.19, 0.12, 0.59], [0.0, 0.3, 0.4]]))
    out = make_dataset("reach-around", tmp_path / "wp", scene=3, waypoints=wp, episodes_per_mode=1,
                       progress=False)
    assert out.is_dir()
    with pytest.raises(ValueError, match="either modes or waypoints"):
        make_dataset("reach-around", tmp_path / "x", modes=[0], waypoints=wp, progress=False)
    with pytest.raises(ValueError, match="unknown mode 'sideways'"):
        make_dataset("reach-around", tmp_path / "x", modes=["sideways"], progress=False)
    with pytest.raises(KeyError, match="unknown env 'nope'"):
        make_dataset("nope", tmp_path / "x", progress=False)
    with pytest.raises(envs.SceneError, match="has no 'waypoints'"):
        make_dataset("reach-around", tmp_path / "x", scene=1, waypoints="scene", progress=False)
    for name, text in (("bad.json", "not json ["), ("bad.yaml", "a: [b")):  # named with the file, not a parser's traceback
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=rf"way-point file {tmp_path / name} is not valid (JSON|YAML) \("):
            make_dataset("reach-around", tmp_path / "x", scene=3, waypoints=tmp_path / name, progress=False)
    (tmp_path / "mixed.json").write_text("[[0.1, 0.2, 0.3], [0.4, 0.5]]")  # points of different sizes
    with pytest.raises(ValueError, match=rf"way-point file {tmp_path / 'mixed.json'}: way-points must be a list of "
                                         r"points of the same size \(\[x, y\] or "):
        make_dataset("reach-around", tmp_path / "x", scene=3, waypoints=tmp_path / "mixed.json", progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", ["pick-place", "kitchen-microwave"])
def test_other_suite_envs_record_through_the_suite_interface(name, tmp_path):
    assert name in envs.SUITE
    out = make_dataset(name, tmp_path / name, modes=[0], episodes_per_mode=1, progress=False)
    meta = read_dataset_meta(out)
    assert meta["env"] == name and meta["episode_modes"] == [0]
    # kitchen's scene 0 has no barrier (an infinite clearance, stored as null); pick-place's obstacles are passed
    assert meta["episode_min_clearance"] == [None] if name == "kitchen-microwave" else meta["episode_min_clearance"][0] > 0


def test_plot_dataset_and_scene_drawing(reach_dataset, tmp_path):
    import matplotlib.pyplot as plt

    from lerobot_pdp.envs.plotting import draw_scene, plot_dataset, plot_trajectories

    png = plot_dataset(reach_dataset, tmp_path / "fig" / "reach.png", scene=1)
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="was recorded in 'reach-around' .*not 'avoiding'"):
        plot_dataset(reach_dataset, tmp_path / "other.png", env="avoiding")
    with pytest.raises(FileNotFoundError, match="is not a LeRobotDataset folder"):
        plot_dataset(tmp_path / "nope", tmp_path / "nope.png")
    cut = tmp_path / "cut"  # a data file cut off while written: named, not pyarrow's "<Buffer>"
    shutil.copytree(reach_dataset, cut)
    data = sorted((cut / "data").glob("*/*.parquet"))[0]
    data.write_bytes(data.read_bytes()[:1000])
    with pytest.raises(ValueError, match=rf"recording {cut}: {data.relative_to(cut)} is unreadable"):
        plot_dataset(cut, tmp_path / "cut.png")
    assert not (tmp_path / "other.png").exists()
    fig, ax = plt.subplots()
    draw_scene(ax, "avoiding", 3, "xy")
    assert len(ax.patches) == 6 + 2 - 1 + 4  # posts + walls - removed post + sealing boxes
    handles = plot_trajectories(ax, [np.zeros((3, 4)), np.ones((3, 4))], [5, "novel"], envs.SUITE["avoiding"].mode_names,
                                "xy", (0, 1))
    assert [h.get_label() for h in handles] == ["5: L-M-2", "novel"]
    with pytest.raises(ValueError, match="plane"):
        draw_scene(ax, "reach-around", 0, "xx")
    plt.close(fig)
    fig, ax = plt.subplots()
    draw_scene(ax, "pick-place", 0, "yz")  # obstacles A and B, start / object / target markers
    assert len(ax.patches) == 2 and len(ax.lines) == 3
    plt.close(fig)


def test_way_points_are_drawn_in_order_on_plots(reach_dataset, tmp_path):
    """Way-points (a scene's, a file's as search --waypoints takes them, or those a dataset was recorded along)
    are drawn numbered, joined in order, with their pass radius when given; a file that does not fit the env is
    named."""
    import matplotlib.pyplot as plt

    from lerobot_pdp.envs.plotting import draw_waypoints, plot_dataset

    fig, ax = plt.subplots()
    route = draw_waypoints(ax, [[0.1, 0.2, 0.3], [0.2, 0.3, 0.3], [0.4, 0.3, 0.2]], "xz", radius=0.05)
    assert route.get_label() == "way-points (pass within 0.05 m)"
    assert [t.get_text() for t in ax.texts] == ["1", "2", "3"] and len(ax.patches) == 3
    assert np.allclose(ax.lines[0].get_xydata(), [[0.1, 0.3], [0.2, 0.3], [0.4, 0.2]])  # x, z in order
    assert draw_waypoints(ax, [[0.1, 0.2]], "xz") is None  # 2-D points have no z
    plt.close(fig)
    assert cli_main(["plot-dataset", str(reach_dataset), "--scene", "3", "--waypoints", "scene", "--out",
                     str(tmp_path / "wp.png")]) == 0
    bad = tmp_path / "wp.json"
    bad.write_text("[[0.1, 0.2]]")
    with pytest.raises(ValueError, match=f"{bad}: reach-around way-points are points of 3 coordinates"):
        plot_dataset(reach_dataset, tmp_path / "bad.png", waypoints=str(bad))
    assert not (tmp_path / "bad.png").exists()
    recorded = make_dataset("reach-around", tmp_path / "along", scene=3, episodes_per_mode=1, waypoints="scene",
                            progress=False)
    assert read_dataset_meta(recorded)["waypoints"]
    assert plot_dataset(recorded, tmp_path / "along.png").is_file()


def test_cli_make_and_plot(tmp_path, capsys):
    out = tmp_path / "cli_ds"
    rc = cli_main(["make-dataset", "--env", "reach-around", "--scene", "2", "--modes", "left-wide",
                   "--episodes-per-mode", "2", "--seed", "3", "--out", str(out), "--no-progress"])
    assert rc == 0 and (out / "meta" / "info.json").is_file()
    assert read_dataset_meta(out)["episode_modes"] == [3, 3]
    rc = cli_main(["plot-dataset", str(out), "--out", str(tmp_path / "p.png")])
    assert rc == 0 and (tmp_path / "p.png").is_file()
    rc = cli_main(["plot-dataset", str(out), "--out", str(tmp_path / "plot")])  # no suffix: a PNG by that name
    assert rc == 0 and (tmp_path / "plot").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli_main(["plot-dataset", str(out), "--out", str(tmp_path / "p.svg")]) == 0
    assert (tmp_path / "p.svg").read_text().lstrip().startswith("<?xml")
    capsys.readouterr()
    assert cli_main(["plot-dataset", str(out), "--env", "reach-arond", "--out", str(tmp_path / "q.png")]) == 2
    assert "unknown env 'reach-arond'" in capsys.readouterr().err  # a typo, not "recorded in another env"
    rc = cli_main(["make-dataset", "--env", "reach-around", "--out", str(out), "--no-progress"])
    assert rc == 2 and "already exists" in capsys.readouterr().err


def test_a_recording_without_the_policys_camera_names_it_and_the_recording_flags(synthetic_meta):
    from lerobot_pdp.demonstration import check_recording

    need = {"observation.state": (2,), "observation.environment_state": (2,), "observation.images.top": (3, 40, 40),
            "action": (2,)}
    with pytest.raises(ValueError, match=r"lacks 'observation.images.top' \(it has no camera\)\. Record with the "
                                         r"robot/env .* \(pdp_sim: --robot.camera_names, --robot.camera_size\)"):
        check_recording(synthetic_meta.root, 0, need)
