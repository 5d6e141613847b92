"""Choose a training setting (e.g. PDP's FiLM form) on the validation split, by the rule validation.py uses.

Each candidate is a finished ``lerobot-pdp benchmark --split validation`` folder that trained the method with
one setting, the current setting first; ``validation.choose_training_setting`` scores them (mean success
over every scene and seed) and keeps the current setting unless another beats it by more than one standard
error. Writes the record as JSON:

    .venv/bin/python scripts/choose_training_setting.py --method pdp --setting film \\
        --candidate mlp=runs/avoiding_val affine=runs/avoiding_val_affine \\
        --out docs/results/avoiding/validation_film.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lerobot_pdp.atomic import write_text_atomic
from lerobot_pdp.benchmark.validation import choose_training_setting


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="pdp")
    ap.add_argument("--setting", required=True, help="what the candidates vary, e.g. film")
    ap.add_argument("--candidate", nargs="+", required=True, metavar="NAME=DIR",
                    help="validation benchmark folders (each with results.json), the current setting first")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    bad = [item for item in args.candidate if "=" not in item]
    if bad:
        ap.error(f"--candidate takes NAME=DIR, got {bad[0]!r}")
    folders = {k: Path(v) for k, v in (item.split("=", 1) for item in args.candidate)}
    missing = [f"{d}/results.json" for d in folders.values() if not (d / "results.json").is_file()]
    if missing:
        ap.error(f"no results file at {missing[0]}: give finished `benchmark --split validation` folders")
    rec = choose_training_setting(args.method, args.setting,
                                  {k: json.loads((d / "results.json").read_text()) for k, d in folders.items()})
    write_text_atomic(args.out, json.dumps(rec, indent=1))
    for row in rec["candidates"]:
        scenes = " ".join(f"{k} {sum(v) / len(v):.0%}" for k, v in row["success"].items())
        print(f"{row['candidate']}: {row['score']:.1%}  ({scenes})")
    print(f"chosen: {rec['chosen']} -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
