"""The explorer (``lerobot-pdp explore``): its panels as plain functions and through a launched Gradio app
(``gradio_client``), the landscape cache, adapted checkpoints saved from it, the no-env and camera cases, bad input
named; and, marked slow, a real headless Chromium clicking the map.

The policies are small and untrained with random FiLM layers (as in test_latent_search.py), so latents act
differently; rollouts are cut to 30 steps. The tests check the machinery, not that a latent succeeds.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from policies import saved_steerable_checkpoint

from lerobot_pdp import PDPPolicy
from lerobot_pdp.checkpoint import ADAPTATION_INFO

gradio = pytest.importorskip("gradio", reason='the explorer needs Gradio: pip install -e ".[explore]"')

STEPS = 30
BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")  # Debian's chromium
DRIVER = shutil.which("chromedriver")  # Debian's chromium-driver (no selenium-manager download: offline)


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> tuple[Path, Path]:
    return saved_steerable_checkpoint(tmp_path_factory.mktemp("explore"))


@pytest.fixture(scope="module")
def explorer(made, tmp_path_factory):
    from lerobot_pdp.explorer import Explorer

    ckpt, data = made
    return Explorer(ckpt, env="reach-around", scene="3", rollouts=2, max_steps=STEPS,
                    cache_dir=tmp_path_factory.mktemp("cache"), dataset=data)


@pytest.fixture(scope="module")
def served(explorer):
    """The app on a free local port; closed after the module's tests."""
    from lerobot_pdp.explorer_app import launch

    app = launch(explorer, port=None, block=False)  # Gradio binds the first free port it tries (no race)
    try:
        yield app.local_url
    finally:
        app.close()


def _pixel_of(explorer, view, z) -> tuple[float, float]:
    return view.to_pixel(explorer.map.projection.to_map(np.asarray(z))[0])


# ------------------------------------------------------------------------------------------------ plain functions


def test_a_click_on_the_map_gives_the_latent_under_it(explorer):
    view = explorer.render_map()
    assert view.image.ndim == 3 and view.image.dtype == np.uint8
    z = explorer.mode_latent(2)
    sel = explorer.pick(view, *_pixel_of(explorer, view, z))
    (x0, x1), (y0, y1) = view.xlim, view.ylim
    per_pixel = max((x1 - x0) / (view.box[2] - view.box[0]), (y1 - y0) / (view.box[3] - view.box[1]))
    assert np.allclose(sel.z, z, atol=1.5 * per_pixel)
    assert explorer.render_map().box == view.box  # the map does not move between clicks
    with pytest.raises(ValueError, match="outside the latent map's axes"):
        explorer.pick(view, view.image.shape[1] - 2, 2)  # the trace panels, not the scatter


def test_rollouts_from_a_latent_report_success_and_collisions(explorer):
    run = explorer.rollout(explorer.mode_latent(0))
    assert len(run.outcomes) == 2 and len(run.modes) == 2
    assert all(o.states.shape[1] >= 3 and len(o.states) > 1 for o in run.outcomes)
    assert run.summary().startswith(f"success {run.successes}/2") and f"collisions {run.collisions}/2" in run.summary()
    assert run.image.ndim == 3 and run.image.shape[1] > run.image.shape[0]  # three views side by side
    again = explorer.rollout(explorer.mode_latent(0))  # same seeds: the same rollouts
    assert np.array_equal(again.outcomes[0].states, run.outcomes[0].states)
    fig = Figure()
    handles = explorer.draw_rollouts(fig.subplots(), run.outcomes, run.modes, "xy")
    assert handles[-1].get_label() == "the scene's way-points"  # scene 3 admits a route: it is drawn


def test_interpolation_runs_from_one_mode_to_the_other(explorer):
    za, zb = explorer.mode_latent(0), explorer.mode_latent("5: right-wide")
    start, line = explorer.interpolate(0, "5: right-wide", 0.0)
    end, _ = explorer.interpolate(0, 5, 1.0, path="elliptical")
    mid, _ = explorer.interpolate(0, 5, 0.5)
    assert np.allclose(start.z, za, atol=1e-6) and np.allclose(end.z, zb, atol=1e-5)
    assert np.allclose(mid.z, (za + zb) / 2, atol=1e-5)
    assert np.allclose(line[0], za, atol=1e-6) and np.allclose(line[-1], zb, atol=1e-6)
    assert "from mode 0 (over-tight) to mode 5 (right-wide)" in mid.source
    with pytest.raises(ValueError, match=r"t must be within \[0, 1\]"):
        explorer.interpolate(0, 5, 1.5)
    with pytest.raises(KeyError, match="no mode 42"):
        explorer.interpolate(0, 42, 0.5)


def test_a_fitted_demonstration_is_marked_with_its_error_ratio(explorer, made):
    _, data = made
    sel, mark = explorer.fit(data, 3)
    assert len(sel.z) == 2 and mark.z == sel.z and "episode 3" in mark.label
    assert sel.provenance["source"] == "fit_latent" and sel.provenance["demonstration"]["episode"] == 3
    assert "error ratio" in sel.source
    plain, marked = explorer.render_map(), explorer.render_map(sel, mark)
    assert plain.image.shape == marked.image.shape and not np.array_equal(plain.image, marked.image)
    with pytest.raises(ValueError, match=r"episode 99 is out of range: .* has episodes 0-7"):
        explorer.fit(data, 99)
    with pytest.raises(FileNotFoundError, match="nowhere does not exist"):
        explorer.fit(data / "nowhere", 0)
    with pytest.raises(FileNotFoundError, match=r"meta is not a LeRobotDataset \(no meta/info.json\)"):
        explorer.fit(data / "meta", 0)
    for episode in ("abc", 0.9):
        with pytest.raises(ValueError, match=r"episode must be a whole number .*episodes 0-7"):
            explorer.fit(data, episode)


def test_the_success_landscape_is_cached_per_checkpoint_scene_and_grid(explorer, monkeypatch):
    seen = []
    land = explorer.landscape(grid=2, rollouts=1, progress=lambda f, d: seen.append(f))
    assert not land.from_cache and land.success.shape == (2, 2) and land.cache.is_file()
    assert seen[-1] == 1.0 and all(0 <= f <= 1 for f in seen)
    saved = json.loads(land.cache.read_text())
    assert saved["key"]["env"] == "reach-around" and saved["key"]["grid"] == 2 and len(saved["key"]["checkpoint"]) == 64
    assert not list(land.cache.parent.glob(".*tmp*"))  # written whole: no temporary file left

    def no_rollouts(*a, **kw):
        raise AssertionError("a cached landscape must not roll out again")

    monkeypatch.setattr(explorer, "run_latents", no_rollouts)
    again = explorer.landscape(grid=2, rollouts=1)
    assert again.from_cache and np.array_equal(again.success, land.success) and again.cache == land.cache
    assert explorer.landscape_image(again).ndim == 3
    with pytest.raises(AssertionError, match="must not roll out"):  # another grid is another cache entry
        explorer.landscape(grid=4, rollouts=1)
    # a request that would hold the app for hours is refused before any rollout (from Python: limit=None)
    with pytest.raises(ValueError, match=r"a 500 x 500 grid at 8 rollout\(s\) each is 2000000 rollouts, over the "
                                         r"limit of 1024 per request"):
        explorer.landscape(grid=500, rollouts=8)
    with pytest.raises(AssertionError, match="must not roll out"):
        explorer.landscape(grid=500, rollouts=8, limit=None)


def test_a_landscape_stopped_between_batches_caches_nothing(explorer):
    """The page's *stop* raises from the progress report, which comes between batches of rollouts: the request
    ends with that error, no cache entry is written, and the explorer runs the next request as before."""
    calls = []

    def stop_at_the_second_batch(fraction, what):
        calls.append(fraction)
        if len(calls) == 2:
            raise RuntimeError("the landscape was stopped; nothing was cached")

    before = set(explorer.cache_dir.glob("landscape-*.json")) if explorer.cache_dir.is_dir() else set()
    with pytest.raises(RuntimeError, match="the landscape was stopped"):
        explorer.landscape(grid=5, rollouts=2, progress=stop_at_the_second_batch)
    assert len(calls) == 2 and calls[1] < 1.0  # stopped midway, not at the end
    assert set(explorer.cache_dir.glob("landscape-*.json")) == before
    assert explorer.landscape(grid=1, rollouts=1).success.shape == (1, 1)  # the lock and envs were given back


def test_a_latent_far_off_the_map_is_pointed_at_not_zoomed_out_to(explorer):
    """A typed latent far from the training latents (1e9) widens the map's view by at most two spans each side,
    so the training latents stay a map and clicks stay near them; an arrow at the edge says where it went."""
    from lerobot_pdp.explorer import Selection

    base = explorer.render_map()
    span = max(base.xlim[1] - base.xlim[0], base.ylim[1] - base.ylim[0])
    near = explorer.render_map(Selection([float(v) * 1.2 for v in explorer.mode_latent(0)], "typed", {}))
    far = explorer.render_map(Selection([1e9, 1e9], "typed", {}))
    for view in (near, far):
        assert view.xlim[1] - view.xlim[0] <= 5.2 * span and view.ylim[1] - view.ylim[0] <= 5.2 * span
    texts = [t.get_text() for t in explorer.map.axes.texts]
    assert "selection off the map" not in texts  # the marks are removed after each picture
    assert not np.array_equal(far.image, base.image)


def test_a_saved_adapted_checkpoint_acts_at_the_selected_latent(explorer, tmp_path):
    sel, _ = explorer.interpolate(0, 5, 0.25)
    out = explorer.save_adapted(sel, tmp_path / "adapted")
    info = json.loads((out / ADAPTATION_INFO).read_text())
    assert info["source"].startswith("explorer") and info["scene"].startswith("scene 3") and info["env"] == "reach-around"
    assert "latent chosen in the explorer" in (out / "README.md").read_text()
    policy = PDPPolicy.from_pretrained(out)
    policy.eval()
    assert torch.allclose(policy.active_latent[0], torch.tensor(sel.z), atol=1e-6)
    assert torch.allclose(policy.current_latent(1)[0], torch.tensor(sel.z), atol=1e-6)
    obs = {"observation.state": torch.zeros(1, policy.config.input_features["observation.state"].shape[0])}
    obs.update({k: torch.zeros(1, *f.shape) for k, f in policy.config.input_features.items() if k not in obs})
    assert torch.isfinite(policy.select_action(obs)).all()
    with pytest.raises(FileExistsError, match="exists"):
        explorer.save_adapted(sel, out)
    with pytest.raises(ValueError, match="lies inside the checkpoint"):  # it would copy itself in
        explorer.save_adapted(sel, explorer.checkpoint / "adapted")
    assert not (explorer.checkpoint / "adapted").exists()


def test_without_an_env_the_decoder_view_replaces_rollouts(made):
    from lerobot_pdp.explorer import Explorer

    ckpt, data = made
    ex = Explorer(ckpt, dataset=data)
    assert not ex.has_env and "no env" in ex.describe()
    image = ex.decoder_view(ex.mode_latent(1), frames=2, samples=2)
    assert image.ndim == 3 and image.shape[0] > 50
    assert ex.render_map().image.shape == ex.render_map().image.shape
    with pytest.raises(ValueError, match="need an env"):
        ex.rollout(ex.mode_latent(1))
    with pytest.raises(ValueError, match="need an env"):
        ex.landscape(2, 1)
    with pytest.raises(ValueError, match="needs a recorded episode: start with --dataset DATA"):
        Explorer(ckpt).decoder_view(ex.mode_latent(1))
    assert ex.decoder_episode(ex.mode_latent(1)) == (0, "its first")  # not known to be the training data


def test_the_decoder_view_compares_a_latent_with_the_training_episode_nearest_it(made, tmp_path):
    """A mode's latent meets a demonstration of that mode, not the dataset's episode 0 whatever its mode."""
    from lerobot_pdp.explorer import Explorer

    ckpt, data = made
    named = Path(shutil.copytree(ckpt, tmp_path / "ckpt"))
    (named / "train_config.json").write_text(json.dumps({"dataset": {"root": str(data)}}))
    ex = Explorer(named)
    table = ex.policy.behavior_table()
    for mode in (1, 3):
        episode, why = ex.decoder_episode(ex.mode_latent(mode))
        assert why == "the training episode nearest z" and set(table["mode"][table["episode"] == episode]) == {mode}
    assert ex.decoder_view(ex.mode_latent(3), frames=1, samples=1).ndim == 3


def test_without_an_env_or_a_recording_a_latent_is_still_selected_and_saved(made, tmp_path):
    """The real robot's case, the checkpoint copied without its data: the map, interpolation and saving work; the
    page says the decoder's view needs a recording and how to give one."""
    from gradio_client import Client

    from lerobot_pdp.explorer import Explorer
    from lerobot_pdp.explorer_app import launch

    ckpt, _ = made
    ex = Explorer(ckpt)
    assert ex.dataset is None
    app = launch(ex, port=None, block=False)
    try:
        client = Client(app.local_url, verbose=False)
        _, decoder_png, summary, latent = client.predict("0.3, -0.2", api_name="/select")
        assert latent == "0.3, -0.2" and decoder_png is None
        assert "the decoder's view needs a recorded episode: start with --dataset DATA" in summary
        note = client.predict(str(tmp_path / "adapted"), api_name="/save")
        assert "wrote" in note and (tmp_path / "adapted" / ADAPTATION_INFO).is_file()
    finally:
        app.close()
    assert PDPPolicy.from_pretrained(tmp_path / "adapted").active_latent[0].tolist() == pytest.approx(
        [0.3, -0.2])


def test_a_relative_training_dataset_is_found_from_the_folder_lerobot_train_ran_in(tmp_path, monkeypatch):
    """lerobot-train records --dataset.root and --output_dir as typed; the checkpoint's own path says where that was."""
    from lerobot_pdp.taught import training_data_of

    lab = tmp_path / "lab"
    ckpt = lab / "runs" / "x" / "checkpoints" / "000010" / "pretrained_model"
    ckpt.mkdir(parents=True)
    (lab / "data" / "d" / "meta").mkdir(parents=True)
    (ckpt / "train_config.json").write_text(json.dumps({"dataset": {"root": "data/d"}, "output_dir": "runs/x"}))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert training_data_of(ckpt) == lab / "data" / "d"
    assert training_data_of(Path("../lab/runs/x/checkpoints/000010/pretrained_model")) == lab / "data" / "d"
    (lab / "last").symlink_to(ckpt.parent, target_is_directory=True)  # checkpoints/last is a link to a step
    assert training_data_of(lab / "last" / "pretrained_model") == lab / "data" / "d"
    shutil.rmtree(lab / "data")  # gone: the root as recorded (the message names it)
    assert training_data_of(ckpt) == Path("data/d")
    (ckpt / "train_config.json").write_text('{"dataset": {"root": ')  # cut off while copied
    with pytest.raises(ValueError, match=rf"{ckpt / 'train_config.json'} is not valid JSON"):
        training_data_of(ckpt)
    (ckpt / "train_config.json").write_text('{"dataset": "data/d"}')
    with pytest.raises(ValueError, match=r"names no local dataset root \(dataset.root\): give the training dataset"):
        training_data_of(ckpt)


def test_a_camera_checkpoint_rolls_out_with_its_camera(tmp_path, monkeypatch):
    from lerobot_pdp.explorer import Explorer

    monkeypatch.setenv("SVT_LOG", "1")  # the AV1 encoder's configuration log, per episode: errors only
    ckpt, data = saved_steerable_checkpoint(tmp_path, camera="oblique")
    ex = Explorer(ckpt, env="reach-around", rollouts=1, max_steps=10, cache_dir=tmp_path / "cache", dataset=data)
    assert "observation.images.oblique" in ex.policy.config.input_features
    assert len(ex.rollout(ex.mode_latent(0)).outcomes) == 1
    read = []  # the decoder's view reads and encodes a recorded episode once, not at every click
    demo_windows = ex.policy.demo_windows
    monkeypatch.setattr(ex.policy, "demo_windows", lambda *a, **k: (read.append(a), demo_windows(*a, **k))[1])
    for _ in range(2):
        assert ex.decoder_view(ex.mode_latent(0), frames=1, samples=1, episode=0).ndim == 3
    assert len(read) == 1
    # another env, one without the checkpoint's camera: named as another env's checkpoint, not as a bad camera alone
    with pytest.raises(ValueError, match=rf"--env avoiding does not match checkpoint {ckpt}: .*unknown camera 'oblique'"):
        Explorer(ckpt, env="avoiding", rollouts=1, max_steps=10, cache_dir=tmp_path / "cache")


def test_explore_on_a_taken_port_names_the_port_before_loading(made, capsys, tmp_path):
    import socket

    from lerobot_pdp.cli import main

    ckpt, _ = made
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert main(["explore", str(ckpt), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"port {port} is not free" in err and "--port" in err and "Traceback" not in err
    # numbers out of range, refused by argparse before anything loads; LeRobot's layout points to its checkpoint
    for flag, value, said in (("--port", "99999", "must be 1..65535, got 99999"), ("--rollouts", "0", "must be >= 1"),
                              ("--max-steps", "0", "must be >= 1")):
        with pytest.raises(SystemExit):
            main(["explore", str(ckpt), flag, value])
        assert f"argument {flag}: {said}" in capsys.readouterr().err
    last = tmp_path / "train" / "checkpoints" / "last"
    (last / "pretrained_model").mkdir(parents=True)
    for f in ckpt.iterdir():
        if f.is_file():
            (last / "pretrained_model" / f.name).write_bytes(f.read_bytes())
    assert main(["explore", str(last)]) == 2
    assert f"did you mean {last / 'pretrained_model'}?" in capsys.readouterr().err


def test_bad_input_is_named(made, tmp_path):
    from lerobot_pdp.explorer import GRADIO_HINT, Explorer, Selection, import_gradio

    ckpt, _ = made
    with pytest.raises(FileNotFoundError, match="no such checkpoint folder"):
        Explorer(tmp_path / "missing")
    half = tmp_path / "half"
    half.mkdir()
    (half / "config.json").write_text(json.dumps({"type": "pdp"}))
    with pytest.raises(FileNotFoundError, match="holds no model.safetensors"):
        Explorer(half)
    (half / "model.safetensors").write_bytes(b"")
    (half / "config.json").write_text('{"type": "pdp", "latent_dim": ')
    with pytest.raises(ValueError, match=rf"{half / 'config.json'} is not valid JSON"):
        Explorer(half)
    with pytest.raises(ValueError, match=r"--env avoiding does not match .*observation.state"):
        Explorer(ckpt, env="avoiding")
    with pytest.raises(KeyError, match="unknown env"):
        Explorer(ckpt, env="no-such-env")
    with pytest.raises(FileNotFoundError, match="recording .*nope does not exist"):  # before loading anything
        Explorer(ckpt, dataset=tmp_path / "nope")
    from lerobot_pdp.envs.recording import make_dataset

    other = make_dataset("avoiding", tmp_path / "other", scene=0, episodes_per_mode=1, modes=[0], progress=False)
    with pytest.raises(ValueError, match=r"does not match the checkpoint"):  # at start-up, not at the first click
        Explorer(ckpt, dataset=other)
    ex = Explorer(ckpt)
    with pytest.raises(ValueError, match=r"give a LeRobotDataset folder \(the folder box is empty\)"):
        ex.fit("  ", 0)
    with pytest.raises(ValueError, match=r"grid must be an integer >= 1, got None"):  # an emptied number box
        Explorer(ckpt, env="reach-around").landscape(None, 1)
    (tmp_path / "a_file").write_text("")
    with pytest.raises(FileExistsError, match=r"a_file is a file, not a folder: give a new folder"):
        ex.save_adapted(Selection([0.0, 0.0], "typed", {}), tmp_path / "a_file" / "sub")
    with pytest.raises(ValueError, match="expected 2 finite numbers"):
        ex.latent("1, 2, 3")
    with pytest.raises(ValueError, match="expected 2 numbers"):
        ex.latent("one, two")
    assert ex.far_note(ex.mode_latent(0)) == ""  # a latent far outside the training ones is said beside it
    assert "far outside the training latents" in ex.far_note("1e6, 1e6")
    assert 'pip install "lerobot_policy_pdp[explore]"' in GRADIO_HINT
    import sys

    saved = sys.modules.get("gradio")
    sys.modules["gradio"] = None  # as if not installed
    try:
        with pytest.raises(ImportError, match=r"\[explore\]"):
            import_gradio()
    finally:
        sys.modules["gradio"] = saved


def test_the_cli_names_a_missing_checkpoint(tmp_path, capsys):
    from lerobot_pdp.cli import main

    assert main(["explore", str(tmp_path / "missing"), "--env", "reach-around"]) == 2
    assert "no such checkpoint folder" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ the served app


def test_the_app_through_gradio_client(served, explorer, made, tmp_path):
    from gradio_client import Client

    _, data = made
    client = Client(served, verbose=False)
    view = explorer.render_map()
    px, py = _pixel_of(explorer, view, explorer.mode_latent(4))
    map_png, rollout_png, summary, latent = client.predict(px, py, api_name="/pick")
    assert Path(map_png).is_file() and Path(rollout_png).is_file()
    assert "success" in summary and "collisions" in summary and "map point" in summary
    assert np.allclose([float(v) for v in latent.split(",")], explorer.mode_latent(4), atol=0.02)

    choices = explorer.mode_choices()
    *_, summary, latent = client.predict(choices[0], choices[5], "linear", 0.5, api_name="/interpolate")
    assert "interpolation from mode 0 (over-tight) to mode 5 (right-wide)" in summary and "success" in summary
    *_, summary, _ = client.predict(str(data), 2, None, api_name="/fit")
    assert "fit to episode 2" in summary and "error ratio" in summary
    note = client.predict(str(tmp_path / "adapted"), api_name="/save")
    assert "wrote" in note and (tmp_path / "adapted" / ADAPTATION_INFO).is_file()
    assert json.loads((tmp_path / "adapted" / ADAPTATION_INFO).read_text())["source"] == "fit_latent"
    land_png, note = client.predict(3, 1, api_name="/landscape")  # (a 3 x 3 grid, one rollout each)
    assert Path(land_png).is_file() and "computed and cached" in note
    _, note = client.predict(3, 1, api_name="/landscape")
    assert "read from the cache" in note
    *_, summary, latent = client.predict("0.01, 0.02", api_name="/select")
    assert latent == "0.01, 0.02" and "success" in summary
    with pytest.raises(Exception, match="expected 2 finite numbers"):
        client.predict("1, 2, 3", api_name="/select")
    with pytest.raises(Exception, match="exists"):
        client.predict(str(tmp_path / "adapted"), api_name="/save")
    with pytest.raises(Exception, match=r"fit steps must be a whole number >= 0 \(0: the checkpoint's fit_steps\), got -5"):
        client.predict(str(data), 2, -5, api_name="/fit")


def test_a_visitors_stop_ends_its_own_landscape_not_anothers(served, explorer, monkeypatch):
    """Two visitors (two gradio_client sessions): B's stop while A's landscape is computed leaves A's to finish;
    A's own stop ends it. The first progress report of each landscape waits for the test to have sent the stop
    (the rollouts are real; only their report is held), so the stop lands while the landscape runs."""
    import threading

    from gradio_client import Client

    started, go = threading.Event(), threading.Event()
    run_latents = explorer.run_latents

    def held(latents, n, progress=None):
        def report(fraction, what):
            if not started.is_set():
                started.set()
                assert go.wait(60), "the test never released the landscape"
            progress(fraction, what)  # raises when this visitor's stop is set
        return run_latents(latents, n, report)

    monkeypatch.setattr(explorer, "run_latents", held)
    a, b = Client(served, verbose=False), Client(served, verbose=False)
    for stopper, grid, stopped in ((b, 6, False), (a, 7, True)):  # grids no other test computed: not cached
        started.clear(), go.clear()
        job = a.submit(grid, 1, api_name="/landscape")
        assert started.wait(60), "the landscape did not start"
        stopper.predict(api_name="/stop_landscape")  # outside the queue: answered while the landscape runs
        go.set()
        if stopped:
            with pytest.raises(Exception, match="the landscape was stopped"):
                job.result(timeout=120)
        else:
            _, note = job.result(timeout=120)
            assert "computed and cached" in note
    _, note = a.predict(7, 1, api_name="/landscape")  # A's stop ended one landscape, not the next
    assert "computed and cached" in note


# ------------------------------------------------------------------------------------------------ a real browser


@pytest.mark.slow
def test_a_person_clicks_the_map_in_a_browser(made, tmp_path, monkeypatch):
    """Headless Chromium (Debian's chromium + chromium-driver) clicks a mode's point on the map; the rollout
    plot appears. The screenshot is kept under pytest's tmp dir and copied to $PDP_TEST_ARTIFACTS when set
    (docs/figures/explorer/explorer.png is one)."""
    from lerobot_pdp.explorer import Explorer
    from lerobot_pdp.explorer_app import launch

    if BROWSER is None or DRIVER is None:
        pytest.skip("no chromium / chromedriver on PATH: install them with `apt-get install -y chromium "
                    "chromium-driver` (make install and make test do it as root)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install selenium (the dev extra has it)")
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    options = webdriver.ChromeOptions()
    options.binary_location = BROWSER
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--window-size=1400,1800"):
        options.add_argument(arg)
    ckpt, data = made
    monkeypatch.chdir(data.parent)  # the page shows the folders as given: relative ones, no machine's paths
    explorer = Explorer(Path(ckpt.name), env="reach-around", scene="3", rollouts=4, max_steps=STEPS,
                        cache_dir=tmp_path / "cache", dataset=Path(data.name))
    app = launch(explorer, port=None, block=False)
    driver = webdriver.Chrome(service=webdriver.ChromeService(executable_path=DRIVER), options=options)
    try:
        driver.get(app.local_url)
        wait = WebDriverWait(driver, 120)
        img = wait.until(lambda d: d.find_element(By.CSS_SELECTOR, "#latent-map img"))
        wait.until(lambda d: d.execute_script("return arguments[0].complete && arguments[0].naturalWidth > 0", img))
        view = explorer.render_map()
        px, py = _pixel_of(explorer, view, explorer.mode_latent(3))
        natural_w, natural_h = driver.execute_script("return [arguments[0].naturalWidth, arguments[0].naturalHeight]", img)
        rect = driver.execute_script("var r = arguments[0].getBoundingClientRect(); return [r.width, r.height]", img)
        scale = min(rect[0] / natural_w, rect[1] / natural_h, 1.0)
        # a stray click (on the trace panels right of the map's axes): a message in the summary, nothing covers the map
        ActionChains(driver).move_to_element_with_offset(img, round(0.42 * natural_w * scale), 0).click().perform()
        stray = wait.until(lambda d: "Not done" in d.find_element(By.ID, "summary").text
                           and d.find_element(By.ID, "summary").text)
        assert "outside the latent map's axes" in stray
        # selenium's offsets are from the element's centre; the picture is centred in it
        dx, dy = (px - natural_w / 2) * scale, (py - natural_h / 2) * scale
        ActionChains(driver).move_to_element_with_offset(img, round(dx), round(dy)).click().perform()
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#result img"))
        summary = wait.until(lambda d: "success" in d.find_element(By.ID, "summary").text
                             and d.find_element(By.ID, "summary").text)
        assert "map point" in summary
        latent = driver.find_element(By.CSS_SELECTOR, "#latent textarea").get_attribute("value")
        assert np.allclose([float(v) for v in latent.split(",")], explorer.mode_latent(3), atol=0.03)
        # the stray click's toast is closed as a person would (its close button), then the picture fades in
        for button in driver.find_elements(By.CSS_SELECTOR, ".toast-close"):
            with contextlib.suppress(Exception):  # one that already closed itself
                button.click()
        WebDriverWait(driver, 15).until(lambda d: not [t for t in d.find_elements(By.CSS_SELECTOR, ".toast-body")
                                                      if t.is_displayed()])
        time.sleep(1.0)
        shot = tmp_path / "explorer.png"
        driver.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000
        if os.environ.get("PDP_TEST_ARTIFACTS"):
            dest = Path(os.environ["PDP_TEST_ARTIFACTS"])
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy(shot, dest / shot.name)
    finally:
        driver.quit()
        app.close()


def test_the_space_app_builds_the_same_app_from_environment_variables(made, monkeypatch):
    import runpy

    ckpt, data = made
    monkeypatch.setenv("PDP_CHECKPOINT", str(ckpt))
    monkeypatch.setenv("PDP_DATASET", str(data))
    monkeypatch.delenv("PDP_ENV", raising=False)
    app = runpy.run_path(str(Path(__file__).resolve().parents[1] / "examples" / "explorer" / "app.py"),
                         run_name="space")["demo"]
    assert isinstance(app, gradio.Blocks)
    names = {d.api_name for d in app.fns.values() if d.api_name}
    assert {"pick", "select", "interpolate", "fit", "save"} <= names and "landscape" not in names  # no env


def test_unlabelled_data_and_a_larger_latent_map_through_the_pca_plane(tmp_path):
    """No mode labels (one instruction for every episode): the map colours discovered clusters and the modes to
    interpolate between are those clusters; with latent_dim 3 a click maps back through the PCA plane."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from policies import small_policy

    from lerobot_pdp.explorer import Explorer

    from synthetic import write_dataset

    data = write_dataset(tmp_path / "data", episodes_per_mode=3, task="reach the goal")
    policy = small_policy(LeRobotDatasetMetadata("local/synthetic", root=data), latent_dim=3, num_inference_steps=4)
    policy.save_pretrained(tmp_path / "ckpt")
    ex = Explorer(tmp_path / "ckpt", dataset=data)
    assert ex.modes.discovered and ex.map.projection.pca is not None and "discovered" in ex.describe()
    view = ex.render_map()
    target = ex.map.projection.to_map(ex.mode_latent(ex.mode_choices()[0]))[0]
    sel = ex.pick(view, *view.to_pixel(target))
    assert len(sel.z) == 3
    assert np.allclose(ex.map.projection.to_map(np.asarray(sel.z))[0], target, atol=0.05 * np.ptp(view.xlim))
    mid, line = ex.interpolate(ex.mode_choices()[0], ex.mode_choices()[-1], 0.5)
    assert len(mid.z) == 3 and len(line[0]) == 3
    assert ex.decoder_view(sel.z, frames=2, samples=2).ndim == 3
