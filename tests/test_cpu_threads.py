"""PDP chooses torch's CPU threads deliberately: half the usable cores unless the user chose."""

import logging

import pytest
import torch

from lerobot_pdp import PDPConfig
from lerobot_pdp.cpu_threads import USER_THREAD_VARS, apply_cpu_threads, auto_threads, usable_cores


@pytest.fixture
def threads(monkeypatch):
    """``run(requested, start)``: torch's thread count after applying ``requested`` from ``start`` threads,
    with no thread variable in the environment; the process's own count is restored afterwards."""
    for var in USER_THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    before = torch.get_num_threads()

    def run(requested, start: int) -> int:
        torch.set_num_threads(start)
        apply_cpu_threads(requested)
        return torch.get_num_threads()

    yield run
    torch.set_num_threads(before)


def test_auto_takes_half_the_usable_cores_and_says_so(threads, caplog):
    start = max(2, usable_cores())
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.cpu_threads"):
        n = threads(None, start)
    assert n == auto_threads() == max(1, usable_cores() // 2) < start  # half of at least 2: always lowered
    assert "auto: half the usable cores" in caplog.text and "--policy.cpu_threads" in caplog.text


def test_auto_never_raises_the_count_and_leaves_an_explicit_environment_alone(threads, monkeypatch):
    assert threads(None, start=1) == 1  # a parent that gave this process one thread keeps it at one
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads(None, start=2) == 2  # the user's OMP_NUM_THREADS wins


def test_explicit_counts(threads):
    assert threads(3, start=1) == 3
    assert threads(0, start=2) == 2  # 0: torch's own setting, untouched


def test_negative_thread_count_is_refused_by_the_config():
    with pytest.raises(ValueError, match=r"cpu_threads must be >= 0 .* got -1"):
        PDPConfig(cpu_threads=-1)


def test_building_a_policy_applies_its_config(synthetic_meta, threads):
    from policies import small_policy

    torch.set_num_threads(2)
    small_policy(synthetic_meta, cpu_threads=1)
    assert torch.get_num_threads() == 1
