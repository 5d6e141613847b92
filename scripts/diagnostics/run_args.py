"""What the diagnostics share: the benchmark run folder they explain, its env and scene, the run's evaluation
record and the scene's demonstration, each refused with an error that names what is missing."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def add_run_args(ap: argparse.ArgumentParser, scene: bool = True) -> None:
    """The positional run folder, ``--env`` and (with ``scene``) ``--scene``."""
    ap.add_argument("run", type=Path, help="a benchmark run directory <out>/runs/pdp/seed<k> (pretrained_model/, eval.json)")
    ap.add_argument("--env", required=True)
    if scene:
        ap.add_argument("--scene", type=lambda v: int(v) if v.isdigit() else v, required=True,
                        help="a shifted scene: 1, 2, 3 or a validation scene (val1, ...)")


def eval_record(ap: argparse.ArgumentParser, run: Path, needed_for: str) -> dict[str, Any]:
    """The run's ``eval.json`` (what the benchmark fitted, its seed); ``needed_for`` says why in the error."""
    meta_file = run / "eval.json"
    if not meta_file.is_file():
        ap.error(f"{run} has no eval.json: run the benchmark on it first ({needed_for})")
    return json.loads(meta_file.read_text())


def scene_demo(ap: argparse.ArgumentParser, suite, run: Path, scene: int | str) -> dict[str, Any]:
    """The demonstration the benchmark adapts to in ``scene``, kept in the run's output folder; made there as the
    benchmark makes it (``ensure_demo``) when the run did not evaluate that scene."""
    from lerobot_pdp.benchmark.data import demo_episode, ensure_demo

    if not (run / "pretrained_model").is_dir():
        ap.error(f"{run} is not a benchmark run directory (no pretrained_model/)")
    root, _ = ensure_demo(suite, run.parents[2], scene)
    return demo_episode(root)
