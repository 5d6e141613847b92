"""Faster LeRobotDataset delta queries on LeRobot 0.6.1: one column read per key, not whole rows.

LeRobot <= 0.6.1 answers every ``delta_timestamps`` query (``DatasetReader._query_hf_dataset``) through
``hf_dataset[key][indices]``. LeRobot always sets a custom transform on its HF dataset, and since
``datasets`` 4.4 a custom format makes that lookup fetch and convert *every* column of the rows (and copy the
dataset's ``Features`` each time) to return one of them. On our datasets that is ~85 % of the time to load
a training item. Upstream answers the queries through cached ``select_columns`` views since
huggingface/lerobot#4314, merged after 0.6.1; this module backports that idea for the LeRobot versions that
lack it, so ``lerobot-train`` (any policy: PDP and the baselines load data the same way) reads only the
columns it asked for. The items are identical (``tests/test_column_views.py``); the speed-up is measured in
``benchmarks/bench_loader.py``.

It changes a LeRobot class, so it is never switched on by importing the policy: call :func:`install` (in
Python), or start a process with ``LEROBOT_PDP_COLUMN_VIEWS=1`` and the plugin's import installs it (that is
how the benchmark's ``lerobot-train`` processes get it). ``LEROBOT_PDP_COLUMN_VIEWS=0`` vetoes both.

Why a patch and not our own dataset class: ``lerobot-train`` builds LeRobot's dataset itself. Why on the
instance and not the class: its loader workers are spawned processes that unpickle the dataset, where a
class patched in the parent is the unpatched original; so the fix travels with each reader (a picklable
callable in its ``__dict__``; unpickling it imports this module), set by a wrapper around
``DatasetReader.__init__`` that :func:`install` puts in place.
"""

from __future__ import annotations

import logging
import os

import torch

ENV_VAR = "LEROBOT_PDP_COLUMN_VIEWS"
# The newest LeRobot release whose reader reads whole rows (huggingface/lerobot#4314 came after it).
LAST_AFFECTED_LEROBOT = "0.6.1"

_logger = logging.getLogger(__name__)
_announced = False


class ColumnViewQuery:
    """``DatasetReader._query_hf_dataset`` answered from one single-column view per key.

    ``select_columns`` is a zero-copy projection of the Arrow table that keeps LeRobot's (column-wise)
    torch transform, so ``view[rows][key]`` returns exactly what the original returned. Views are built
    lazily in each process and rebuilt when the reader loads a new ``hf_dataset``.
    """

    def __init__(self, reader) -> None:
        self.reader = reader
        self._views: dict = {}
        self._source = None

    def __getstate__(self) -> dict:
        # Views are cheap to rebuild; a loader worker builds its own from the unpickled hf_dataset.
        return {"reader": self.reader}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["reader"])

    def __call__(self, query_indices: dict[str, list[int]]) -> dict:
        reader = self.reader
        if reader.hf_dataset is not self._source:
            self._views, self._source = {}, reader.hf_dataset
        to_relative = reader._absolute_to_relative_idx
        result: dict = {}
        for key, q_idx in query_indices.items():
            if key in reader._meta.video_keys:
                continue
            rows = q_idx if to_relative is None else [to_relative[i] for i in q_idx]
            view = self._views.get(key)
            if view is None:
                view = self._views[key] = reader.hf_dataset.select_columns(key)
            result[key] = torch.stack(view[rows][key])
        return result


def affected(lerobot_version: str) -> bool:
    """Whether this LeRobot release answers delta queries with whole-row reads (<= 0.6.1)."""
    from packaging.version import Version

    return Version(lerobot_version) <= Version(LAST_AFFECTED_LEROBOT)


def enabled() -> bool:
    """False when ``LEROBOT_PDP_COLUMN_VIEWS`` vetoes the column views (``0``, ``false``, ``no``, ``off``)."""
    return os.environ.get(ENV_VAR, "").strip().lower() not in ("0", "false", "no", "off")


def requested() -> bool:
    """Whether this process asks for the column views at the plugin's import (``LEROBOT_PDP_COLUMN_VIEWS=1``)."""
    return os.environ.get(ENV_VAR, "").strip().lower() in ("1", "true", "yes", "on")


def child_env() -> dict[str, str]:
    """Environment entries with which a child ``lerobot-train`` installs the column views (unless vetoed here)."""
    return {ENV_VAR: "1"} if enabled() else {}


def active() -> bool:
    """Whether readers made in a child started with :func:`child_env` use column views."""
    import lerobot

    return enabled() and affected(lerobot.__version__)


def install() -> bool:
    """Wrap ``DatasetReader.__init__`` so that every new reader answers delta queries column by column.

    The explicit switch (the plugin's import never calls it unless ``LEROBOT_PDP_COLUMN_VIEWS=1``).
    Idempotent; does nothing (returns False) on a LeRobot release that has the upstream fix, or when
    ``LEROBOT_PDP_COLUMN_VIEWS=0``.
    """
    import lerobot
    from lerobot.datasets.dataset_reader import DatasetReader

    if not active():
        return False
    if getattr(DatasetReader.__init__, "_pdp_column_views", False):
        return True
    original_init = DatasetReader.__init__

    def __init__(self, *args, **kwargs):
        original_init(self, *args, **kwargs)
        if not enabled():  # read per reader, so a process can still turn it off after import
            return
        self._query_hf_dataset = ColumnViewQuery(self)
        global _announced
        if not _announced and self.delta_indices is not None:
            _announced = True
            _logger.info(
                "lerobot_pdp: reading delta-timestamp frames one column at a time (LeRobot %s reads whole "
                "rows; fixed upstream in huggingface/lerobot#4314); %s=0 turns this off",
                lerobot.__version__, ENV_VAR,
            )

    __init__._pdp_column_views = True
    __init__.__wrapped__ = original_init
    DatasetReader.__init__ = __init__
    return True
