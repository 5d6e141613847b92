"""LeRobotDataset delta queries through single-column views (``lerobot_pdp.column_views``) return exactly
what LeRobot's whole-row queries return, in this process and in spawned loader workers."""

from __future__ import annotations

import pickle

import pytest
import torch

from lerobot_pdp import column_views


@pytest.fixture(autouse=True, scope="module")
def _installed():
    """The explicit switch (importing the policy never patches LeRobot), for this module's tests only: LeRobot's
    reader is restored after them, so no other test in this process reads datasets through the views."""
    from lerobot.datasets.dataset_reader import DatasetReader

    original = DatasetReader.__init__
    column_views.install()
    yield
    DatasetReader.__init__ = original


def _dataset(root, delta_timestamps, episodes=None):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset("local/synthetic", root=root, delta_timestamps=delta_timestamps, episodes=episodes)


def _whole_rows(ds):
    """The same dataset answering delta queries LeRobot's own way (the class method)."""
    ds.reader.__dict__.pop("_query_hf_dataset", None)
    return ds


def _assert_same_items(a, b):
    assert len(a) == len(b)
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert x.keys() == y.keys(), i
        for k in x:
            if torch.is_tensor(x[k]):
                assert x[k].dtype == y[k].dtype and torch.equal(x[k], y[k]), (i, k)
            else:
                assert x[k] == y[k], (i, k)


# Past and future frames beyond episode edges, so the padding masks are exercised too.
DELTAS = {"observation.state": [-0.2, -0.1, 0.0], "observation.environment_state": [-0.1, 0.0],
          "action": [-0.1, 0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]}


def test_reader_uses_column_views_when_installed(synthetic_dataset):
    import lerobot

    assert column_views.affected(lerobot.__version__)  # the pinned LeRobot (0.6.1) needs it
    ds = _dataset(synthetic_dataset, DELTAS)
    assert isinstance(ds.reader.__dict__.get("_query_hf_dataset"), column_views.ColumnViewQuery)


@pytest.mark.parametrize("episodes", [None, [3, 7, 8, 21]], ids=["all", "subset"])
def test_items_identical_to_whole_row_queries(synthetic_dataset, episodes):
    views = _dataset(synthetic_dataset, DELTAS, episodes)
    rows = _whole_rows(_dataset(synthetic_dataset, DELTAS, episodes))
    _assert_same_items(views, rows)
    assert views.reader._query_hf_dataset._views.keys() == DELTAS.keys()  # the views answered


def test_images_stored_in_parquet_identical(tmp_path):
    """Embedded images are where whole-row reads cost most; the views keep LeRobot's image transform."""
    from synthetic import write_dataset

    root = write_dataset(tmp_path / "img", episodes_per_mode=1, cameras=("top",), image_size=16, video=False)
    deltas = {**DELTAS, "observation.images.top": [-0.1, 0.0]}
    _assert_same_items(_dataset(root, deltas), _whole_rows(_dataset(root, deltas)))


def test_views_travel_to_spawned_loader_workers(synthetic_dataset):
    """lerobot-train's workers are spawned: they unpickle the reader without importing the plugin."""
    ds = _dataset(synthetic_dataset, DELTAS)
    clone = pickle.loads(pickle.dumps(ds.reader))
    query = clone.__dict__["_query_hf_dataset"]
    assert isinstance(query, column_views.ColumnViewQuery) and query.reader is clone and not query._views

    rows = _whole_rows(_dataset(synthetic_dataset, DELTAS))
    loader = torch.utils.data.DataLoader(ds, batch_size=16, num_workers=1, multiprocessing_context="spawn")
    for batch, start in zip(loader, range(0, 48, 16), strict=False):
        expected = torch.utils.data.default_collate([rows[i] for i in range(start, start + 16)])
        for k in DELTAS:
            assert torch.equal(batch[k], expected[k]), k


def test_views_follow_a_reloaded_hf_dataset(synthetic_dataset):
    ds = _dataset(synthetic_dataset, DELTAS)
    ds[0]
    first = ds.reader._query_hf_dataset._views["action"]
    ds.reader.load_and_activate()  # LeRobot reloads hf_dataset, e.g. after new episodes are written
    ds[0]
    assert ds.reader._query_hf_dataset._views["action"] is not first


def test_turned_off_by_environment_variable(synthetic_dataset, monkeypatch):
    monkeypatch.setenv(column_views.ENV_VAR, "0")
    assert "_query_hf_dataset" not in _dataset(synthetic_dataset, DELTAS).reader.__dict__


def test_only_lerobot_releases_without_the_upstream_fix():
    assert column_views.affected("0.6.0") and column_views.affected("0.6.1")
    assert not column_views.affected("0.6.2") and not column_views.affected("0.7.0")
