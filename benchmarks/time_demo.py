"""`make demo` timed end to end, as the README quotes it: wall, CPU and peak memory of the whole job (the
command's children, from ``getrusage``), each ``lerobot-train``'s own seconds (the benchmark's
``train_info.json``), and the table the run produced, written as one JSON record.

    .venv/bin/python benchmarks/time_demo.py --out docs/results/reach-around/quick_seed0/demo_timing.json

Runs ``make demo DEMO_OUT=<a fresh folder>`` (nothing reused; ``--demo-out`` to keep it elsewhere) from the
repository root. Time it alone: anything else on the machine's cores is in the figure.
"""

from __future__ import annotations

import argparse
import datetime
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="the JSON record to write")
    ap.add_argument("--demo-out", type=Path, default=None,
                    help="the demo's output folder (must not exist; default: a fresh temporary one)")
    args = ap.parse_args()
    if args.demo_out is not None and args.demo_out.exists():
        ap.error(f"--demo-out {args.demo_out} exists: the demo would reuse what it holds")
    sys.path.insert(0, str(ROOT))
    from lerobot_pdp.atomic import write_text_atomic
    from lerobot_pdp.benchmark.machine import cpu_model

    with tempfile.TemporaryDirectory(prefix="pdp-demo-") as tmp:
        demo = (args.demo_out or Path(tmp) / "demo").resolve()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        subprocess.run(["make", "demo", f"DEMO_OUT={demo}"], cwd=ROOT, check=True)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        results = json.loads((demo / "results.json").read_text())
        trained = {m: json.loads(p.read_text())["seconds"]
                   for m in results["methods"] if (p := demo / "runs" / m / "seed0" / "train_info.json").is_file()}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    record = {
        "command": "make demo DEMO_OUT=<fresh dir>",
        "script": "benchmarks/time_demo.py",
        "date": datetime.date.today().isoformat(),
        "commit": commit.strip() or None,
        "cpu": cpu_model(),
        "wall_s": round(wall, 1),
        "user_s": round(after.ru_utime - before.ru_utime, 1),
        "system_s": round(after.ru_stime - before.ru_stime, 1),
        "max_rss_kb": after.ru_maxrss,  # the largest child's (Linux: kilobytes)
        "lerobot_train_s": {m: round(s, 1) for m, s in trained.items()},
        "table": {m: {**{s: round(100 * r[s]["mean"], 1) for s in ("scene0", "scene1", "scene2", "scene3")},
                      "shifted_avg": round(100 * r["shifted_avg"], 1)} for m, r in results["methods"].items()},
    }
    write_text_atomic(args.out, json.dumps(record, indent=1) + "\n")
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
