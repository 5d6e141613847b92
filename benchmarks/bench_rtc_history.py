"""What conditioning a chunk on the published observation history costs under ``lerobot-rollout --inference.type=rtc``.

Side by side, per chunk: the engine's own preprocessing of the chunk's observation (LeRobot's thread does it
once) and PDP's history lookup (:class:`lerobot_pdp.realtime_chunking.PublishedObservations`: find the chunk's
observation among those published, preprocess the ones before it), for a state and one camera at two image
sizes, with the loop having published one more observation than the chunk's (the lookup's usual worst case is
one frame further). PDP's default preprocessor; no policy weights are involved.

    .venv/bin/python benchmarks/bench_rtc_history.py [--calls 50] [--threads 1]

One JSON line per image size on stdout.
"""

from __future__ import annotations

import argparse
import json
import time
import types

import numpy as np
import torch

from lerobot_pdp.benchmark.machine import cpu_model


def _engine(h: int, w: int):
    import lerobot.rollout.inference.rtc as rtc
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_pdp import PDPConfig

    cfg = PDPConfig(device="cpu", push_to_hub=False,
                    input_features={"observation.state": PolicyFeature(FeatureType.STATE, (4,)),
                                    "observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, h, w))},
                    output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))})
    one = {"mean": torch.zeros(4), "std": torch.ones(4), "min": -torch.ones(4), "max": torch.ones(4)}
    image = {"mean": torch.zeros(3, 1, 1), "std": torch.ones(3, 1, 1), "min": torch.zeros(3, 1, 1),
             "max": torch.ones(3, 1, 1)}
    pre, _ = make_pre_post_processors(cfg, dataset_stats={"observation.state": one, "action": one,
                                                          "observation.images.cam": image})
    e = rtc.RTCInferenceEngine.__new__(rtc.RTCInferenceEngine)  # what its thread uses to preprocess
    e._hw_features = {"observation.state": {"dtype": "float32", "shape": (4,), "names": [f"j{i}" for i in range(4)]},
                      "observation.images.cam": {"dtype": "image", "shape": (h, w, 3), "names": None}}
    e._device, e._task, e._robot, e._preprocessor = "cpu", "", types.SimpleNamespace(robot_type="bench"), pre
    # history() reads only the config and the episode count from the policy
    e._policy = types.SimpleNamespace(config=cfg, steering=types.SimpleNamespace(resets=0))
    return e


def _ms(fn, calls: int) -> float:
    for _ in range(3):
        fn()
    t = time.perf_counter()
    for _ in range(calls):
        fn()
    return 1000 * (time.perf_counter() - t) / calls


def main() -> None:
    from lerobot_pdp.realtime_chunking import PublishedObservations, _preprocess

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--calls", type=int, default=50)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    for h, w in [(96, 96), (480, 640)]:
        e = _engine(h, w)
        frames = [{**{f"j{i}": float(k + i) for i in range(4)}, "cam": rng.integers(0, 255, (h, w, 3), dtype=np.uint8)}
                  for k in range(4)]
        published = PublishedObservations(e._policy.config.n_obs_steps)
        for obs in frames:
            published.published(e, obs)
        batch = _preprocess(e, frames[-2])  # the chunk's observation; the loop published one more since
        assert published.history(e._policy, batch)[0] is not None
        engine_ms = _ms(lambda: _preprocess(e, frames[-2]), args.calls)  # noqa: B023
        history_ms = _ms(lambda: published.history(e._policy, batch), args.calls)  # noqa: B023
        print(json.dumps({"bench": "rtc_history", "image": [h, w], "n_obs_steps": published.n_obs_steps,
                          "engine_preprocess_ms": round(engine_ms, 3), "history_ms": round(history_ms, 3),
                          "ratio": round(history_ms / engine_ms, 2), "threads": args.threads,
                          "cpu": cpu_model()}))


if __name__ == "__main__":
    main()
