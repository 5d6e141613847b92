"""Modes without labels: clustering the training latents recovers the demonstrated routes."""

import logging
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_policy
from sklearn.metrics import adjusted_rand_score

from lerobot_pdp import PDPConfig
from lerobot_pdp.modes import cluster_episodes


@pytest.fixture(scope="module")
def embedded(synthetic_meta):
    """PDP on the synthetic 4-mode dataset with its trajectory VAE trained (L_embed only: seconds)."""
    torch.manual_seed(0)
    p = make_policy(PDPConfig(device="cpu", push_to_hub=False, down_dims=(16, 32)), ds_meta=synthetic_meta)
    opt = torch.optim.Adam(p.model.vae.parameters(), lr=1e-3)
    for _ in range(400):
        loss, _ = p.model.embedding_loss("cpu")
        opt.zero_grad()
        loss.backward()
        opt.step()
    p.eval()
    return p


@pytest.mark.parametrize("space", ["traces", "latents"])
def test_discover_modes_recovers_the_four_routes(embedded, space):
    found = embedded.discover_modes(space=space)
    true = {int(e): int(m) for e, m in zip(embedded.model.bank.episode, embedded.model.bank.mode, strict=True)}
    episodes = sorted(true)
    ari = adjusted_rand_score([true[e] for e in episodes], [found.labels[e] for e in episodes])
    assert found.k == 4 and ari >= 0.9, (found.k, ari, found.silhouette)
    assert found.space == space and found.outliers == []
    assert set(found.means) == set(range(4)) and all(m.shape == (2,) for m in found.means.values())
    assert max(found.silhouette, key=found.silhouette.get) == 4
    assert embedded.discover_modes(k=3, space=space).k == 3
    if space == "traces":  # each cluster's mean latent is its episodes' mean latent, as with the latents
        z = embedded.behavior_latents().detach().numpy()
        ep = embedded.model.bank.episode.numpy()
        for c, mean in found.means.items():
            members = [e for e, lab in found.labels.items() if lab == c]
            assert np.allclose(mean.numpy(), z[np.isin(ep, members)].mean(0), atol=1e-5)


def test_discover_modes_argument_errors_are_named(embedded):
    with pytest.raises(ValueError, match="space must be one of .*got 'pixels'"):
        embedded.discover_modes(space="pixels")
    with pytest.raises(ValueError, match="max_k bounds the search over k of the latents"):
        embedded.discover_modes(max_k=6)
    assert embedded.discover_modes(max_k=6, space="latents").k == 4


def test_clustering_trace_distances_finds_close_modes_a_latent_map_merges():
    """Two routes much closer to each other than to the rest, yet far apart relative to their own spread
    (kitchen's front and low): HDBSCAN on the divergences keeps them apart; an outlier joins its nearest mode
    and is reported."""
    from lerobot_pdp.modes import cluster_distances, episode_distances

    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [0.3, 0.0], [5.0, 0.0], [0.0, 6.0], [7.0, 7.0]])
    pts = np.repeat(centres, 6, axis=0) + rng.normal(0, 0.01, (30, 2))
    pts = np.vstack([pts, [[12.0, 12.0]]])  # a lone episode, nearest the last route
    truth = np.r_[np.repeat(np.arange(5), 6), 4]
    # two phases per episode: divergences (squared distances) of each phase add up
    half = pts / np.sqrt(2)
    n = len(pts)
    d = np.zeros((2 * n, 2 * n))
    sq = ((half[:, None] - half[None]) ** 2).sum(-1)
    d[:n, :n] = d[n:, n:] = sq
    episodes, dist = episode_distances(d, np.r_[np.arange(n), np.arange(n)], np.r_[np.zeros(n), np.ones(n)])
    assert (episodes == np.arange(n)).all()
    assert np.allclose(dist, np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)))
    labels, k, noise = cluster_distances(dist)
    assert k == 5 and adjusted_rand_score(truth, labels) == 1.0 and noise == [30]
    labels, k, noise = cluster_distances(dist[:30, :30], k=5)  # k given: agglomerative, nothing left out
    assert k == 5 and adjusted_rand_score(truth[:30], labels) == 1.0 and noise == []
    assert labels[0] == 0  # ids numbered by their first episode
    with pytest.raises(ValueError, match=r"k must be between 1 and the number of training episodes \(31\), got 32"):
        cluster_distances(dist, k=32)
    with pytest.raises(ValueError, match="needs at least 6 training episodes"):
        cluster_distances(dist[:5, :5])
    with pytest.raises(ValueError, match="different numbers of phases"):
        episode_distances(np.zeros((3, 3)), np.array([0, 0, 1]), np.array([0, 1, 0]))


def test_mode_latents_fall_back_to_discovered_modes_with_a_warning(embedded, caplog):
    labeled = embedded.mode_latents()
    saved = embedded.model.bank.mode.clone()
    try:
        embedded.model.bank.mode = torch.full_like(saved, -1)  # an instruction-string dataset
        with caplog.at_level(logging.WARNING):
            means = embedded.mode_latents()
        assert "no mode labels" in caplog.text and "discover_modes" in caplog.text
        assert len(means) == 4
        # every discovered mean lies next to one labeled mode's mean (same clusters, other ids)
        nearest = {min(labeled, key=lambda m: float((labeled[m] - z).norm())) for z in means.values()}
        assert nearest == set(labeled)
        embedded.set_latent(means[0])  # and steers like any latent
        assert torch.equal(embedded.active_latent[0], means[0])
    finally:
        embedded.model.bank.mode = saved
        embedded.set_latent(None)  # the module's policy is shared: back to its default latent


def test_cluster_choice_errors_are_named():
    feats = np.random.default_rng(0).normal(size=(10, 2))
    with pytest.raises(ValueError, match=r"k must be between 1 and the number of training episodes \(10\), got 11"):
        cluster_episodes(feats, k=11)
    with pytest.raises(ValueError, match="choosing k needs at least 3 training episodes"):
        cluster_episodes(feats[:2])
    with pytest.raises(ValueError, match="max_k must be at least 2 .*got 1"):
        cluster_episodes(feats, max_k=1)
    labels, k, _ = cluster_episodes(feats, k=1)
    assert k == 1 and set(labels.tolist()) == {0}


def test_k_is_searched_up_to_half_the_episodes_and_a_binding_bound_is_reported(caplog):
    """More modes than the old fixed bound of 12 (16 routes, 3 demonstrations each) are found by default;
    an explicit smaller bound that decides k is reported."""
    rng = np.random.default_rng(0)
    centres = rng.uniform(-10, 10, (16, 3))
    feats = np.repeat(centres, 3, axis=0) + rng.normal(0, 0.01, (48, 3))
    truth = np.repeat(np.arange(16), 3)
    labels, k, scores = cluster_episodes(feats)
    assert k == 16 and max(scores) == 24 and adjusted_rand_score(truth, labels) == 1.0  # searched to 48 // 2
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.modes"):
        assert cluster_episodes(feats, max_k=2)[1] == 2
    assert "chose k = 2, the largest candidate" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.modes"):
        cluster_episodes(feats)  # k = 16 below the default bound (48 // 2): nothing to report
    assert "largest candidate" not in caplog.text


def test_latent_map_cli_draws_any_checkpoint_labels_or_clusters(embedded, tmp_path, capsys):
    from lerobot_pdp.cli import main

    ckpt = tmp_path / "ckpt"
    embedded.save_pretrained(ckpt)
    assert main(["latent-map", str(ckpt), "--out", str(tmp_path / "map.png")]) == 0
    assert (tmp_path / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["latent-map", str(ckpt), "--out", str(tmp_path / "clusters.png"), "--k", "4"]) == 0
    assert (tmp_path / "clusters.png").stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt", "clusters.png", "map.png"]  # no temp files
    capsys.readouterr()
    assert main(["latent-map", str(tmp_path), "--out", str(tmp_path / "x.png")]) == 2
    assert f"{tmp_path} is not a PDP checkpoint folder (config.json + model.safetensors)" in capsys.readouterr().err
    layout = tmp_path / "run" / "checkpoints" / "last"
    layout.mkdir(parents=True)
    ckpt.rename(layout / "pretrained_model")  # LeRobot's training layout: pointed to the checkpoint below
    assert main(["latent-map", str(layout), "--out", str(tmp_path / "x.png")]) == 2
    assert f"did you mean {layout / 'pretrained_model'}?" in capsys.readouterr().err
    layout.joinpath("pretrained_model").rename(ckpt)
    assert main(["latent-map", str(tmp_path / "nope"), "--out", str(tmp_path / "x.png")]) == 2
    assert f"no such checkpoint folder: {tmp_path / 'nope'}" in capsys.readouterr().err
    assert main(["latent-map", str(ckpt / "config.json"), "--out", str(tmp_path / "x.png")]) == 2
    assert f"{ckpt / 'config.json'} is a file, not a checkpoint folder" in capsys.readouterr().err
    assert main(["latent-map", str(ckpt), "--out", str(tmp_path / "x.png"), "--k", "0"]) == 2
    assert "--k must be >= 1 (clusters to colour by), got 0" in capsys.readouterr().err


INSTRUCTION = "move the point from the bottom to the top, around the disc"


@pytest.fixture(scope="module")
def instruction_dataset(tmp_path_factory):
    """The synthetic 4-mode data with one language instruction as every episode's task: no labels."""
    from synthetic import write_dataset

    return write_dataset(tmp_path_factory.mktemp("instr") / "instr", episodes_per_mode=3, seed=1, task=INSTRUCTION)


def _meta(root):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    return LeRobotDatasetMetadata("local/instr", root=root)


def test_instruction_task_strings_are_no_labels_and_a_label_file_adds_them(instruction_dataset, tmp_path, capsys):
    import json
    import shutil

    from policies import small_policy

    from lerobot_pdp.cli import main

    p = small_policy(_meta(instruction_dataset))
    assert (p.model.bank.mode == -1).all() and p.config.mode_names is None
    root = tmp_path / "labelled"
    shutil.copytree(instruction_dataset, root)
    true = [m for _ in range(3) for m in (0, 1, 2, 3)]  # write_dataset's episode order
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps({"episodes": {str(e): m for e, m in enumerate(true)},
                                  "names": {"0": "left, tight", "3": "right, wide"}}))
    assert main(["label-modes", str(root), "--labels", str(labels)]) == 0
    q = small_policy(_meta(root))
    assert q.model.bank.mode.tolist() == true
    assert q.config.mode_names == {"0": "left, tight", "1": "1", "2": "2", "3": "right, wide"}
    assert sorted(q.mode_latents()) == [0, 1, 2, 3]
    # the task strings are untouched
    from lerobot_pdp.episodes import read_episodes

    assert {e["task"] for e in read_episodes(root, []).values()} == {INSTRUCTION}


@pytest.mark.parametrize(("content", "message"), [
    ({"episodes": {"0": "left"}}, r"episode 0 has mode 'left'; expected an integer mode id >= 0"),
    ({"episodes": {"first": 1}}, r"episode key 'first' is not an episode index"),
    ({"episodes": {"0": 1}, "names": {"1": 5}}, r"name of mode 1 is 5; expected a string"),
    ({"episodes": {"0": 1}}, r"labels must cover episodes 0\.\.11 exactly; missing \[1, 2,"),
    ([1, 2], r'expected \{"episodes"'),
])
def test_bad_label_files_are_named_errors(instruction_dataset, tmp_path, capsys, content, message):
    import json

    from lerobot_pdp.cli import main

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(content))
    assert main(["label-modes", str(instruction_dataset), "--labels", str(bad)]) == 2
    assert re.search(message, capsys.readouterr().err)
    assert not (instruction_dataset / "meta" / "mode_labels.json").exists()
    assert main(["label-modes", str(instruction_dataset), "--labels", str(tmp_path / "none.json")]) == 2
    assert f"label file {tmp_path / 'none.json'} does not exist (--labels: a JSON file" in capsys.readouterr().err


def test_labels_from_task_strings_and_their_absence(synthetic_dataset, instruction_dataset, tmp_path, capsys):
    import shutil

    from lerobot_pdp.cli import main
    from lerobot_pdp.episodes import read_mode_labels

    root = tmp_path / "synthetic"
    shutil.copytree(synthetic_dataset, root)
    assert main(["label-modes", str(root), "--from-tasks"]) == 0
    labels, names = read_mode_labels(root)
    assert len(labels) == 40 and names == {0: "left-tight", 1: "left-wide", 2: "right-tight", 3: "right-wide"}
    capsys.readouterr()
    assert main(["label-modes", str(instruction_dataset), "--from-tasks"]) == 2
    assert "carries no 'mode <id>: <name>' label; give --labels" in capsys.readouterr().err
    assert main(["label-modes", str(tmp_path / "missing"), "--from-tasks"]) == 2
    assert f"dataset folder {tmp_path / 'missing'} does not exist" in capsys.readouterr().err
    (tmp_path / "file.json").write_text("{}")
    assert main(["label-modes", str(tmp_path / "file.json"), "--from-tasks"]) == 2
    assert "file.json is a file; give a LeRobotDataset v3 folder" in capsys.readouterr().err


def test_label_modes_from_tasks_replaces_a_stale_label_file(synthetic_dataset, tmp_path, capsys):
    """A label file that covers only some episodes (as a resumed recording used to leave) is replaced whole, not
    read first (reading it is what training refuses)."""
    import json
    import shutil

    from lerobot_pdp.cli import main
    from lerobot_pdp.episodes import read_mode_labels

    root = tmp_path / "synthetic"
    shutil.copytree(synthetic_dataset, root)
    stale = root / "meta" / "mode_labels.json"
    stale.write_text(json.dumps({"episodes": {"0": 3, "1": 3}}))
    assert main(["label-modes", str(root), "--from-tasks"]) == 0
    labels, _ = read_mode_labels(root)
    assert labels == {e: e % 4 for e in range(40)}  # write_dataset's order: modes 0..3 in turn
    assert sorted(p.name for p in stale.parent.iterdir() if "mode_labels" in p.name) == ["mode_labels.json"]
    assert "wrote" in capsys.readouterr().out


def test_latent_map_draws_unlabelled_behaviors_in_grey(tmp_path):
    """Episodes with a mode label and episodes with an instruction only: every behavior is drawn, the unlabelled
    ones as their own grey group, and the title counts them."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from matplotlib.colors import to_rgba
    from policies import small_policy

    from lerobot_pdp.latent_map import UNLABELLED_COLOR, latent_map_figure

    from synthetic import GOAL, MODES, demo_path

    feat = {"dtype": "float32", "shape": (2,)}
    ds = LeRobotDataset.create(repo_id="local/mixed", fps=10, root=tmp_path / "mixed", features={
        "observation.state": {**feat, "names": ["x", "y"]}, "observation.environment_state": {**feat, "names": ["gx", "gy"]},
        "action": {**feat, "names": ["dx", "dy"]}})
    rng = np.random.default_rng(0)
    for m, task in [(0, None), (0, None), (2, None), (2, None), (1, INSTRUCTION), (3, INSTRUCTION)]:
        pos, act = demo_path(m, rng)
        for p, a in zip(pos, act, strict=True):
            ds.add_frame({"observation.state": p, "observation.environment_state": GOAL.astype(np.float32),
                          "action": a, "task": task or f"mode {m}: {MODES[m][0]}"})
        ds.save_episode()
    ds.finalize()
    policy = small_policy(_meta(tmp_path / "mixed"))
    drawn = latent_map_figure(policy)
    try:
        assert drawn.groups.tolist() == [0, 0, 2, 2, -1, -1]
        assert drawn.axes.get_title().startswith("latent map: 6 behaviors (2 unlabelled, grey), coloured by mode label")
        points = {tuple(c.get_facecolor()[0]): len(c.get_offsets()) for c in drawn.axes.collections if len(c.get_offsets())}
        assert sum(points.values()) == 6 and points[to_rgba(UNLABELLED_COLOR)] == 2
        legend = [t.get_text() for t in drawn.axes.get_legend().get_texts()]
        assert legend[-1] == "unlabelled" and legend[0] == f"0: {MODES[0][0]}"  # the id, then its name
    finally:
        import matplotlib.pyplot as plt

        plt.close(drawn.figure)


@pytest.mark.slow
def test_lerobot_train_on_an_instruction_dataset_without_labels(instruction_dataset, tmp_path):
    import json

    from conftest import train_tiny_pdp

    ckpt = train_tiny_pdp(instruction_dataset, tmp_path / "train")
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["type"] == "pdp" and cfg["mode_names"] is None
    from lerobot_pdp import PDPPolicy

    p = PDPPolicy.from_pretrained(ckpt)
    assert len(p.discover_modes(k=4).labels) == 12


def test_a_segmented_policys_map_labels_each_phase_beside_its_points():
    """A pick-place policy's two phases of one mode sit in different places: each phase's points get the mode's
    number beside them (not one number at their mean, where no point is)."""
    import matplotlib.pyplot as plt

    from lerobot_pdp import PDPPolicy
    from lerobot_pdp.latent_map import latent_map_figure

    p = PDPPolicy.from_pretrained(Path(__file__).parent / "data" / "pdp_checkpoints_v2" / "adapted_pick_place")
    drawn = latent_map_figure(p)
    try:
        xy = drawn.projection.to_map(p.behavior_table()["z"])
        phase = p.behavior_phase().cpu().numpy()
        labels = [t for t in drawn.axes.texts if t.get_text().isdigit()]
        assert len(labels) == sum(len(np.unique(phase[drawn.groups == g])) for g in np.unique(drawn.groups))
        span = np.ptp(xy, axis=0).max()
        for t in labels:
            own = xy[drawn.groups == int(t.get_text())]
            assert np.linalg.norm(own - np.asarray(t.xy), axis=1).min() < 0.15 * span, t.get_text()
        # an adapted checkpoint's map marks where its adaptation acts (one diamond per phase latent)
        marks = [c for c in drawn.axes.collections if c.get_label().startswith("active latent")]
        assert len(marks) == 1 and len(p.steering.latent) == 2
        np.testing.assert_allclose(marks[0].get_offsets(), drawn.projection.to_map(p.steering.latent.numpy()),
                                   rtol=1e-5)
    finally:
        plt.close(drawn.figure)


def test_loose_clusters_are_said_to_be_loose(caplog):
    """Routes of one demonstration each form no clusters of their own; when what is found is loose (silhouette
    under 0.5), a warning says that a cluster's mean may lie between routes. Clear clusters: no warning."""
    import logging

    from lerobot_pdp.modes import discover

    rng = np.random.default_rng(0)
    clear = np.concatenate([rng.normal(c, 0.05, (4, 2)) for c in ([0, 0], [3, 0], [0, 3])]).astype(np.float32)
    ring = np.stack([np.cos(np.arange(12) / 2), np.sin(np.arange(12) / 2)], 1).astype(np.float32)  # 12 routes
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.modes"):
        found = discover(clear, np.arange(12), np.zeros(12, int))
        assert found.k == 3 and "loose" not in caplog.text
        found = discover(ring, np.arange(12), np.zeros(12, int))  # by latents: k by silhouette, all weak
    assert found.silhouette[found.k] < 0.5 and "clusters found are loose" in caplog.text


def test_training_says_what_its_behavior_bank_holds(synthetic_meta, caplog):
    """lerobot-train builds the policy from its dataset: one line says the episodes, behaviours and modes read
    (labelled, or none: discovered later), which a run's log otherwise never shows."""
    import dataclasses
    import logging

    from policies import small_policy

    from lerobot_pdp.behavior_bank import bank_summary

    with caplog.at_level(logging.INFO, logger="lerobot_pdp.behavior_bank"):
        p = small_policy(synthetic_meta)
    n = len(p.model.bank.episode)
    assert (f"PDP behavior bank: {synthetic_meta.total_episodes} episode(s), {n} behavior(s); 4 labelled mode(s): "
            "0 (left-tight), 1 (left-wide), 2 (right-tight), 3 (right-wide)") in caplog.text
    from lerobot_pdp.behavior import BehaviorTraces

    t = BehaviorTraces(np.zeros((3, 4, 2)), np.arange(3), np.zeros(3), np.zeros(3), np.full(3, 4),
                       np.full(3, -1), {})
    assert bank_summary(t) == ("3 episode(s), 3 behavior(s); no mode labels (mode_latents() discovers the modes by "
                               "clustering; lerobot-pdp latent-map draws them)")
    assert "1 episode(s) without a label" in bank_summary(dataclasses.replace(t, mode=np.array([0, 1, -1])))


def test_mode_latents_of_too_few_unlabelled_episodes_say_how_to_get_modes(tmp_path, caplog):
    """Four unlabelled episodes are too few to find modes: mode_latents() says to label them or to choose k, which
    then works; the latent map and the explorer show them all the same, one group per episode (said), or in k."""
    from policies import small_policy

    from lerobot_pdp.explorer import Explorer
    from lerobot_pdp.latent_map import latent_map_figure

    from synthetic import write_dataset

    root = write_dataset(tmp_path / "few", episodes_per_mode=1, task=INSTRUCTION)
    policy = small_policy(_meta(root))
    with pytest.raises(ValueError, match=r"mode_latents\(\): the training episodes carry no mode labels, and finding "
                                         r"their modes failed: finding the modes needs at least 6 training episodes "
                                         r".*got 4\. Label them \(`lerobot-pdp label-modes DATASET`.*mode_latents\(k=K\)"):
        policy.mode_latents()
    assert len(policy.discover_modes(k=2).means) == 2 and len(policy.mode_latents(k=2)) == 2
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.latent_map"):
        drawn = latent_map_figure(policy)
    drawn.figure.clf()
    assert "4 training episodes without mode labels: too few to find modes in (6 or more; --k K groups them)" \
        in caplog.text
    policy.save_pretrained(tmp_path / "ckpt")
    assert sorted(Explorer(tmp_path / "ckpt", dataset=root).modes) == [0, 1, 2, 3]  # one mode per episode
    assert sorted(Explorer(tmp_path / "ckpt", dataset=root, k=2).modes) == [0, 1]
