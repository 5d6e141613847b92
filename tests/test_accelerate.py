"""Multi-process training through accelerate: the behavior bank is computed once, every rank holds the same,
and the checkpoint loads and steers.

accelerate's ``--cpu`` launcher starts a single process unless it is given an MPI host file, so two CPU
processes are launched with ``--multi_gpu`` (torchrun underneath) and ``--policy.device=cpu``, which makes
lerobot-train's Accelerator use gloo on the CPU.
"""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import lerobot_cli, run_cli

from lerobot_pdp import distributed
from lerobot_pdp.distributed import (
    agree_across_ranks,
    main_process_first,
    release_process_group_at_exit,
    warn_if_cpu_launch_ran_one_process,
    world,
)


def test_helpers_are_no_ops_in_a_single_process():
    assert world() == (0, 1)
    with main_process_first():
        pass
    assert agree_across_ranks("x", "digest", "note") == ["note"]
    release_process_group_at_exit()
    assert distributed._HELD_GROUPS == []


def test_the_process_group_outlives_its_destruction_until_exit(monkeypatch):
    """lerobot-train destroys the group before its DDP model (whose Reducer would then free it holding the GIL):
    the group is held once, past destroy_process_group, and let go by an exit handler."""
    import atexit

    import torch.distributed as dist

    handlers = []
    monkeypatch.setattr(atexit, "register", handlers.append)
    monkeypatch.setattr(distributed, "_HELD_GROUPS", [])
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        group = dist.distributed_c10d._get_default_group()
        release_process_group_at_exit()
        release_process_group_at_exit()
    finally:
        dist.destroy_process_group()
    assert distributed._HELD_GROUPS == [group] and len(handlers) == 1
    assert group.size() == 1  # still a live object after destroy_process_group
    handlers[0]()
    assert distributed._HELD_GROUPS == []


def test_a_cpu_launch_that_ran_one_process_is_reported(monkeypatch, caplog):
    """What `accelerate launch --cpu --num_processes 2` leaves in the environment of its single process."""
    for k in ("WORLD_SIZE", "PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MV2_COMM_WORLD_SIZE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("ACCELERATE_USE_CPU", "True")
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    assert not warn_if_cpu_launch_ran_one_process()  # --num_processes 1: no MASTER_ADDR, nothing to say
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.distributed"):
        assert warn_if_cpu_launch_ran_one_process()
    assert "--multi_gpu" in caplog.text
    monkeypatch.setenv("WORLD_SIZE", "2")  # a real multi-process launch
    assert not warn_if_cpu_launch_ran_one_process()


@pytest.mark.slow
def test_two_process_cpu_training_computes_the_bank_once_and_the_checkpoint_steers(tmp_path):
    from lerobot_pdp.modeling_pdp import PDPPolicy

    from synthetic import write_dataset

    data = write_dataset(tmp_path / "data", episodes_per_mode=3, seed=0, video=False)
    cache, out = tmp_path / "cache", tmp_path / "train"
    accelerate = str(Path(sys.executable).parent / "accelerate")
    # Every launcher setting is a flag: no `accelerate config` file is needed (nor read for these values).
    proc = run_cli([accelerate, "launch", "--multi_gpu", "--num_processes=2", "--num_machines=1",
                    "--mixed_precision=no", "--dynamo_backend=no", "--main_process_port=0",
                    lerobot_cli("lerobot-train"), "--policy.type=pdp", "--policy.device=cpu",
                    "--policy.push_to_hub=false", "--policy.down_dims=[16,32]", "--policy.vae_hidden_dims=[32,32]",
                    "--dataset.repo_id=local/synthetic", f"--dataset.root={data}", "--steps=4", "--batch_size=4",
                    "--save_freq=4", "--log_freq=2", "--num_workers=0", "--wandb.enable=false",
                    f"--output_dir={out}"],
                   timeout=300, env={"LEROBOT_PDP_CACHE": str(cache), "TQDM_DISABLE": "1"})
    log = proc.stdout + proc.stderr
    assert "Effective batch size: 4 x 2 = 8" in log  # two ranks really trained
    # rank 0 computed delta^X and cached it; rank 1 read the cache (and both hold the same bank)
    banks = re.findall(r"behavior bank: (\d+) behaviors, identical on all 2 ranks \(sha1 (\w+)\); "
                       r"soft-DTW distances: rank 0 computed, rank 1 read from cache", log)
    assert len(banks) == 1, log[-3000:]
    assert len(list(cache.glob("trace_distances_*.npy"))) == 1

    policy = PDPPolicy.from_pretrained(out / "checkpoints" / "last" / "pretrained_model")
    policy.eval()
    n, digest = banks[0]
    assert len(policy.model.bank.traces) == int(n) == 12
    assert policy.model.bank.digest().startswith(digest)  # the checkpoint holds the bank the ranks agreed on
    cached = np.load(next(cache.glob("trace_distances_*.npy")))
    assert np.allclose(policy.model.bank.distances.numpy(), cached, atol=1e-6)
    modes = policy.mode_latents()
    assert sorted(modes) == [0, 1, 2, 3] and all(torch.isfinite(z).all() for z in modes.values())
    res = policy.fit_latent((data, 5), steps=3)
    assert torch.isfinite(res.z).all() and torch.equal(policy.current_latent()[0], res.z)
