"""Success against the rollouts a search spends (``lerobot-pdp search-curves``), on one shifted scene of a trained
benchmark run: CMA-ES over PDP's latent started from the gradient fit (``z_fit``) or from the mode means
(``z_modes``), the gradient fit alone (``fit``, no search rollouts), and a DSRL-style search over LeRobot
``diffusion``'s initial noise with the same optimiser, population rule, rollouts per candidate and budget
(``dp_noise``). With way-points instead of a demonstration (``score="waypoints"``, or ``"waypoints_finish"``: the
way-points, then the task's success, ``WaypointScore(finish=True)``) only the searches that need no demonstration
run.

With the search's confirmation of a new best (``confirm_rollouts``, the default) every budget point b runs its own
search of b rollouts, and its best is evaluated on the protocol's evaluation rollouts of the scene: a shorter search
confirms fewer challengers, so it is not the start of a longer one. Without confirmation each search runs ONCE, at
the largest budget, and for every b the best candidate of its first b rollouts (by the search's own score, as
``search_latent`` keeps its best) is evaluated: the optimiser asks the same populations whatever the budget, so
those candidates are the ones a search of budget b would try (only the sampler noise of a smaller last batch may
differ). ``z_modes`` scores every mode mean first (avoiding: 24 x 2 rollouts), so its points below that budget
are the best of the first modes' means.

The latent searches act under the sampler's own noise (``CandidateRollouts``' per-env latents carry no fitted
chunk noises); where the frozen adaptation also fits one noise per chunk (``settings.FROZEN``), the ``fit`` point
includes them and ``z_fit``'s first candidate, the fit's z alone, does not.

Seeds. Evaluation: the protocol's own for (seed, scene), ``seed * 10_000 + scene_seed_offset(scene) + i`` for
rollout i, as ``benchmark`` evaluates (the fit's point is the benchmark's number for that scene). Search: every
candidate's j-th rollout resets with ``seed * 10_000 + SEARCH_SEED_OFFSET + scene_seed_offset(scene) + j``, the same
for every method of a (seed, scene) and never an evaluation seed of any scene: a point's success is measured on
initial states its search never saw.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import math
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..atomic import write_figure_atomic, write_text_atomic
from ..candidate_rollouts import CandidateRollouts, EnvFactory
from ..folder_lock import hold_folder
from ..latent_search import (
    CONFIRM_ROLLOUTS,
    SearchResult,
    default_popsize,
    make_optimizer,
    optimise,
    search_latent,
)
from ..outcome_scores import Outcome, Score, WaypointScore, resolve_score, waypoint_progress
from .data import check_run_env
from .machine import cpu_model
from .rollouts import RolloutBatch, run_rollouts
from .settings import Method, check_split, frozen_for, scene_seed_offset

logger = logging.getLogger(__name__)

METHODS = ("z_fit", "z_modes", "fit", "dp_noise")
NEEDS_DEMO = ("z_fit", "fit")  # the gradient fit needs a demonstration; way-points are not one
SCORES = ("success", "waypoints", "waypoints_finish")
DEFAULT_BUDGETS = (16, 32, 64, 128, 256, 512)
SEARCH_SEED_OFFSET = 5_000  # search seeds sit this far above the scene's evaluation seeds (docstring)
MAX_EVAL_ROLLOUTS = 4_000  # evaluation seeds of every scene stay below the search seeds of every scene
# DP's sampler starts from x_K ~ N(0, I): CMA-ES's first population around the zero noise with step 1 is a draw
# of DP's own prior, so the search starts where DP samples and moves away only as far as the score pays.
DP_NOISE_SIGMA = 1.0
RECORD, TABLE, FIGURE = "search_curves.json", "search_curves.md", "search_curves.png"
COLORS = {"z_fit": "tab:blue", "z_modes": "tab:orange", "dp_noise": "tab:green"}  # one colour per method in every panel
LABELS = {"z_fit": "z search from the fit", "z_modes": "z search from the mode means", "fit": "gradient fit",
          "dp_noise": "DP noise search (DSRL-style)"}


def check_request(methods: Sequence[str] | None, budgets: Sequence[int], rollouts: int, score: str,
                  rollouts_per_candidate: int, scene: int | str,
                  confirm_rollouts: int = 0) -> tuple[list[str], list[int]]:
    """The methods (default: every one the score allows) and sorted budgets of a request; a ValueError naming the
    value otherwise. Checked before anything is loaded."""
    if score not in SCORES:
        raise ValueError(f"score must be one of {SCORES}, got {score!r}")
    if scene == 0 or scene == "0":
        raise ValueError("scene 0 has no adaptation: give a shifted scene (1-3, the env's zero-mode test scene 4 where "
                         "it ships one, or val<k>)")
    if methods is None:
        methods = [m for m in METHODS if score == "success" or m not in NEEDS_DEMO]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    if score != "success" and any(m in NEEDS_DEMO for m in methods):
        raise ValueError(f"method(s) {[m for m in methods if m in NEEDS_DEMO]} fit a demonstration, which "
                         f"--score {score} does not have: use z_modes and dp_noise")
    k = rollouts_per_candidate
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 1_000:
        raise ValueError(f"rollouts_per_candidate must be an integer in 1..1000, got {k!r}")
    c = confirm_rollouts
    if isinstance(c, bool) or not isinstance(c, int) or not (c == 0 or k < c <= MAX_EVAL_ROLLOUTS):
        raise ValueError(f"confirm_rollouts must be 0 (off) or an integer in {k + 1}..{MAX_EVAL_ROLLOUTS} (more than "
                         f"rollouts_per_candidate, {k}), got {c!r}")
    if not budgets:
        raise ValueError("budgets: give at least one")
    for b in budgets:
        if isinstance(b, bool) or not isinstance(b, int) or b < k:
            raise ValueError(f"budget {b!r} must be an integer >= rollouts_per_candidate ({k}), the price of one "
                             "candidate")
    small = [b for b in budgets if c and b < k + c]
    if small:  # one candidate and its confirmation cost k + c: such a point is its first candidate, unsearched
        logger.warning("search-curves: budget(s) %s pay for less than one candidate and its confirmation (%d + %d "
                       "rollouts): those points are the first candidate only", small, k, c)
    if isinstance(rollouts, bool) or not isinstance(rollouts, int) or not 1 <= rollouts <= MAX_EVAL_ROLLOUTS:
        raise ValueError(f"rollouts must be an integer in 1..{MAX_EVAL_ROLLOUTS} (evaluation seeds stay apart from "
                         f"the search's), got {rollouts!r}")
    return list(dict.fromkeys(methods)), sorted(set(budgets))


def evaluation_seed(seed: int, scene: int | str) -> int:
    """The protocol's first evaluation rollout seed of (training seed, scene)."""
    return seed * 10_000 + scene_seed_offset(scene)


def search_seed(seed: int, scene: int | str) -> int:
    """The first env seed of every candidate of a search on (training seed, scene): no evaluation seed."""
    return evaluation_seed(seed, scene) + SEARCH_SEED_OFFSET


class TimedScore:
    """A score that notes when each rollout was scored: the wall time of a search up to any candidate."""

    def __init__(self, score: str | Score):
        self.score, self.objective = resolve_score(score)
        self.times: list[float] = []
        self.__name__ = getattr(self.score, "__name__", type(self.score).__name__)

    def __call__(self, outcome: Outcome) -> float:
        self.times.append(time.perf_counter())
        return self.score(outcome)

    def describe(self) -> Any:
        return self.objective


# ----------------------------------------------------------------------------- DP: search over the initial noise


class NoiseCandidateRollouts(CandidateRollouts):
    """Candidate DP noises ([horizon, action_dim] each) rolled out together, env b starting every chunk's
    sampler from its candidate's noise (:class:`~lerobot_pdp.benchmark.baselines.PerEnvNoisePolicy`)."""

    @contextlib.contextmanager
    def acting(self, per_env: Tensor) -> Iterator[Any]:
        from .baselines import PerEnvNoisePolicy

        training = self.policy.training
        self.policy.eval()
        try:
            yield PerEnvNoisePolicy(self.policy, per_env)
        finally:
            self.policy.train(training)
            self.policy.reset()


def search_dp_noise(policy: Any, env_factory: EnvFactory, score: str | Score, budget: int, seed: int,
                    rollouts_per_candidate: int, processors: tuple, max_envs: int = 16, confirm_rollouts: int = 0,
                    progress: bool = True) -> SearchResult:
    """CMA-ES over DP's initial noise x_K, one [horizon, action_dim] noise shared by every chunk, as
    ``search_latent`` searches z: the same optimiser (``make_optimizer("cma")``, its default population
    4 + 3 ln D), the starting point (the zero noise, the prior's mean) scored first, ``budget`` rollouts of
    ``rollouts_per_candidate`` each per candidate, the best by (score, success), confirmed as ``search_latent``
    confirms it (``confirm_rollouts``). Candidates' ``latent``: their noise."""
    score_fn, objective = resolve_score(score)
    shape = (int(policy.config.horizon), int(policy.config.action_feature.shape[0]))
    k = rollouts_per_candidate
    result = SearchResult(None, -math.inf, 0.0, [], "cma", seed, budget, k, objective,
                          confirm_rollouts=confirm_rollouts)
    t0 = time.perf_counter()
    bar = tqdm(total=budget // k * k, unit="rollout", desc="DP noise search (cma)", disable=not progress)
    run = NoiseCandidateRollouts(policy, env_factory, k, seed, processors, None, max_envs)

    try:
        optimise(result, run, [torch.zeros(shape)],
                 lambda x0: make_optimizer("cma", x0.reshape(-1).double().numpy(), DP_NOISE_SIGMA, None, None, seed),
                 lambda o, x, i: float(score_fn(o)), budget, bar)
    finally:
        bar.close()
        run.close()
    result.seconds = time.perf_counter() - t0
    return result


# ----------------------------------------------------------------------------- budget points


def best_so_far(result: SearchResult, budgets: Sequence[int]) -> list[tuple[int, int, int]]:
    """(budget, rollouts the search had used within it, index of its best then) per budget, for a search without
    confirmation (every candidate ``rollouts_per_candidate`` rollouts): the best by (score, success) of the
    candidates within the budget, the first of equals, as ``SearchResult.best_at`` reads the search's record."""
    k = result.rollouts_per_candidate
    out = []
    for b in budgets:
        used = min(b // k, len(result.history)) * k
        out.append((b, used, result.best_at(used)))
    return out


def _scene_name(scene: int | str) -> str:
    """How headings name a scene: "scene 3" for a test scene, "val3" for a validation scene."""
    return f"scene {scene}" if str(scene).isdigit() else str(scene)


def summarize(batch: RolloutBatch, waypoints: WaypointScore | None) -> dict[str, Any]:
    """Success and collision over the evaluation rollouts (and, scored by way-points, their mean progress)."""
    d: dict[str, Any] = {"success": batch.success_rate, "collision": batch.collision_rate, "n": len(batch.results)}
    if waypoints is not None:
        d["waypoint_score"] = float(np.mean([waypoint_progress(r.trace, waypoints.waypoints, waypoints.radius)
                                             for r in batch.results]))
    return d


def _sha(path: Path) -> str:
    """A checkpoint's fingerprint: a record is reused for these weights only."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def run_sampler(run_dir: Path) -> dict[str, Any]:
    """The DDIM steps and grid a run was evaluated with (its ``eval.json``), else its checkpoint's own."""
    from .evaluation import checkpoint_sampler

    made = json.loads((run_dir / "eval.json").read_text()) if (run_dir / "eval.json").is_file() else {}
    steps, spacing = checkpoint_sampler(run_dir / "pretrained_model")
    return {"inference_steps": made.get("inference_steps") or steps, "timestep_spacing": made.get("timestep_spacing") or spacing}


def is_quick_run(out: Path) -> bool:
    """Whether ``out`` is a --quick benchmark (its ``results.json``; full without one): which FROZEN row applies."""
    res = out / "results.json"
    return bool(json.loads(res.read_text()).get("quick", False)) if res.is_file() else False


# ----------------------------------------------------------------------------- the measurement


def run_search_curves(out: Path, env: str, scene: int | str, seed: int, dest: Path,
                      budgets: Sequence[int] = DEFAULT_BUDGETS, rollouts: int = 40, score: str = "success",
                      methods: Sequence[str] | None = None, radius: float = 0.05, rollouts_per_candidate: int = 2,
                      dp_out: Path | None = None, device: str = "cpu", max_envs: int = 16,
                      max_episode_steps: int | None = None, confirm_rollouts: int = CONFIRM_ROLLOUTS,
                      progress: bool = True,
                      command: str | None = None) -> dict[str, Any]:
    """Measure the curves of ``methods`` on ``scene`` for the benchmark run ``out/runs/<pdp|dp>/seed<seed>`` (DP's
    under ``dp_out`` when given) and write ``dest``/search_curves.json, .md and .png. A record of the same (method,
    scene, seed, score) made with the same settings and checkpoint is reused. ``max_episode_steps``: shorter
    episodes than the env's (tests). Returns the whole record file."""
    import dataclasses

    import lerobot_pdp.envs  # noqa: F401  (registers the suite)

    from ..envs.recording import check_waypoints
    from ..envs.scene import load_scene
    from ..envs.suite import get_suite_env

    methods, budgets = check_request(methods, budgets, rollouts, score, rollouts_per_candidate, scene, confirm_rollouts)
    scene = int(scene) if isinstance(scene, str) and scene.isdigit() else scene
    check_split("validation" if isinstance(scene, str) else "test", (scene,), [seed], flag=False)
    suite = get_suite_env(env)
    if max_episode_steps is not None:
        suite = dataclasses.replace(suite, max_episode_steps=int(max_episode_steps))
    for folder in dict.fromkeys((Path(out), Path(dp_out or out))):
        check_run_env(folder, suite)
    sc = load_scene(scene, suite.scene_key)
    waypoints = None
    if score != "success":
        if sc.waypoints is None:
            raise ValueError(f"--score {score}: {suite.name} scene {scene} ships no way-points (a scene with a "
                             "feasible training mode); score it by success with its demonstration")
        check_waypoints(suite, np.asarray(sc.waypoints, dtype=float), sc.source)
        waypoints = WaypointScore(sc.waypoints, radius, dims=suite.trace_dims, finish=score == "waypoints_finish")
    runs = {"pdp": Path(out) / "runs" / "pdp" / f"seed{seed}", "dp": Path(dp_out or out) / "runs" / "dp" / f"seed{seed}"}
    for name in [n for n in ("pdp", "dp") if any((m == "dp_noise") == (n == "dp") for m in methods)]:
        if not (runs[name] / "pretrained_model" / "model.safetensors").is_file():
            raise FileNotFoundError(f"no trained {name} run at {runs[name]} (pretrained_model/model.safetensors): "
                                    f"give a benchmark output folder holding runs/{name}/seed{seed}"
                                    + (", another folder's DP run with --dp-results, or leave dp_noise out (--methods "
                                       "z_fit z_modes fit)" if name == "dp" else ""))
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    with hold_folder(dest, "search-curves"):  # one writer: the records are read, extended and rewritten
        curves = _Curves(suite, scene, seed, Path(out), runs, waypoints, rollouts, rollouts_per_candidate, max_envs,
                         confirm_rollouts, device, progress, out_held=Path(out).resolve() == dest.resolve())
        return _record_curves(curves, methods, budgets, score, dest, command)


def _record_curves(curves: _Curves, methods: list[str], budgets: list[int], score: str, dest: Path,
                   command: str | None) -> dict[str, Any]:
    """Measure each method not yet recorded in ``dest`` with these settings; the record file is rewritten after
    each method, so an interrupted run keeps what it measured."""
    record_file = dest / RECORD
    book: dict[str, Any] = json.loads(record_file.read_text()) if record_file.is_file() else {"records": {}}
    book.update(cpu=cpu_model(), threads=torch.get_num_threads())
    c = curves
    common = {"budgets": budgets, "rollouts": c.rollouts, "rollouts_per_candidate": c.k, "max_envs": c.max_envs,
              "evaluation_seeds": [c.eval0, c.eval0 + c.rollouts - 1], "search_seeds": [c.search0, c.search0 + c.k - 1],
              "max_episode_steps": c.suite.max_episode_steps, "device": c.device,
              "objective": "success" if c.waypoints is None else c.waypoints.describe()}
    for method in tqdm(methods, desc=f"search curves {c.suite.name} {c.scene} seed {c.seed}", unit="method",
                       disable=not c.progress):
        name = "dp" if method == "dp_noise" else "pdp"
        settings = {**common, "checkpoint": _sha(c.runs[name] / "pretrained_model" / "model.safetensors"),
                    "sampler": run_sampler(c.runs[name])}
        if method in NEEDS_DEMO:
            settings["adapt"] = c.adapt_kwargs
        if c.confirm_rollouts:  # absent when off: the records made before confirmation existed still match
            settings["confirm_rollouts"] = c.confirm_rollouts
            settings["search_seeds"] = [c.search0, c.search0 + c.confirm_rollouts - 1]
        key = f"{c.suite.name}/{c.scene}/seed{c.seed}/{score}/{method}"
        old = book["records"].get(key)
        if old is not None and old.get("settings") == json.loads(json.dumps(settings)):
            continue
        rec = {"env": c.suite.name, "scene": c.scene, "seed": c.seed, "score": score, "method": method,
               "settings": settings, **c.measure(method, budgets)}
        if command:
            rec["command"] = command
        book["records"][key] = rec
        write_records(book, dest)
    write_records(book, dest)
    return book


class _Curves:
    """The measurements of one (benchmark run, scene, training seed, score): the policies loaded once, the
    gradient fit made once, every point evaluated on the protocol's evaluation rollouts of the scene."""

    def __init__(self, suite: Any, scene: int | str, seed: int, out: Path, runs: dict[str, Path],
                 waypoints: WaypointScore | None, rollouts: int, rollouts_per_candidate: int, max_envs: int,
                 confirm_rollouts: int, device: str, progress: bool, out_held: bool = False):
        self.suite, self.scene, self.seed, self.out, self.runs = suite, scene, seed, out, runs
        self.out_held = out_held  # this process already holds the benchmark folder's lock (dest is that folder)
        self.waypoints, self.rollouts, self.k, self.max_envs = waypoints, rollouts, rollouts_per_candidate, max_envs
        self.confirm_rollouts, self.device, self.progress = confirm_rollouts, device, progress
        self.eval0, self.search0 = evaluation_seed(seed, scene), search_seed(seed, scene)
        self.adapt_kwargs = dict(frozen_for(suite.name, is_quick_run(out), "pdp").get("adapt", {}))
        self._loaded: dict[str, Any] = {}
        self._fitted: dict[str, Any] = {}

    def policy_of(self, name: str) -> tuple[Any, Any, Any]:
        """(policy, preprocessor, postprocessor) of the run ``name`` ("pdp" or "dp"), with its evaluation sampler."""
        if name not in self._loaded:
            from .training import load_policy

            s = run_sampler(self.runs[name])
            self._loaded[name] = load_policy(self.runs[name] / "pretrained_model", s["inference_steps"], self.device,
                                             s["timestep_spacing"])
        return self._loaded[name]

    def _demo(self) -> Path:
        """The scene's demonstration in the benchmark folder, made there (as the benchmark makes it) under that
        folder's lock when it is missing: a benchmark writing the folder meanwhile is named, not raced."""
        from .data import demo_root, ensure_demo

        if (demo_root(self.suite, self.out, self.scene) / "meta" / "pdp_demo.json").is_file() or self.out_held:
            return ensure_demo(self.suite, self.out, self.scene)[0]
        with hold_folder(self.out, "search-curves (making a scene demonstration)"):
            return ensure_demo(self.suite, self.out, self.scene)[0]

    def fit(self) -> dict[str, Any]:
        """The benchmark's adaptation of PDP to the scene's demonstration, evaluated as the benchmark does."""
        if not self._fitted:
            from .data import demo_episode
            from .evaluation import adapt

            policy, pre, post = self.policy_of("pdp")
            demo = demo_episode(self._demo())
            t0 = time.perf_counter()
            actor, info = adapt(Method("pdp", "pdp"), policy, pre, demo, self.seed, **self.adapt_kwargs)
            seconds = time.perf_counter() - t0
            batch = run_rollouts(self.suite, self.scene, actor, pre, post, self.rollouts, self.eval0,
                                 label=f"scene {self.scene}")
            policy.set_latent(None)
            self._fitted.update(z=info["z"], seconds=round(seconds, 2), fit_error_ratio=info.get("fit_error_ratio"),
                                evaluation=summarize(batch, self.waypoints))
        return self._fitted

    def evaluate_latent(self, z: Tensor) -> dict[str, Any]:
        policy, pre, post = self.policy_of("pdp")
        policy.set_latent(z)
        try:
            return summarize(run_rollouts(self.suite, self.scene, policy, pre, post, self.rollouts, self.eval0),
                             self.waypoints)
        finally:
            policy.set_latent(None)

    def evaluate_noise(self, x: Tensor) -> dict[str, Any]:
        from .baselines import FixedNoisePolicy

        policy, pre, post = self.policy_of("dp")
        return summarize(run_rollouts(self.suite, self.scene, FixedNoisePolicy(policy, x[None]), pre, post,
                                      self.rollouts, self.eval0), self.waypoints)

    def search(self, method: str, budget: int, init: Any) -> tuple[SearchResult, list[float]]:
        """One search of ``budget`` rollouts and the wall time after each of its rollouts."""
        timed = TimedScore(self.waypoints if self.waypoints is not None else "success")
        policy, pre, post = self.policy_of("dp" if method == "dp_noise" else "pdp")
        factory = _factory(self.suite, self.scene)
        t0 = time.perf_counter()
        if method == "dp_noise":
            res = search_dp_noise(policy, factory, timed, budget, self.search0, self.k, (pre, post), self.max_envs,
                                  self.confirm_rollouts, self.progress)
        else:
            res = search_latent(policy, factory, timed, budget=budget, init=init, method="cma", seed=self.search0,
                                rollouts_per_candidate=self.k, max_envs=self.max_envs, processors=(pre, post),
                                confirm_rollouts=self.confirm_rollouts, progress=self.progress)
        if res.interrupted:
            raise KeyboardInterrupt
        return res, [t - t0 for t in timed.times]

    def measure(self, method: str, budgets: list[int]) -> dict[str, Any]:
        """One method's record: its points (budget, rollouts used, seconds, the candidate and its evaluation)."""
        rec: dict[str, Any] = {}
        if method == "fit":
            f = self.fit()
            rec["fit"] = {k2: v for k2, v in f.items() if k2 != "evaluation"}
            z = torch.as_tensor(f["z"])
            rec["points"] = [{"budget": 0, "rollouts_used": 0, "seconds": round(f["seconds"], 2),
                              "norm": float(z.norm()), "latent": f["z"], **f["evaluation"]}]
            return rec
        init: Any = "modes"
        if method == "z_fit":
            f = self.fit()
            rec["fit"] = {k2: v for k2, v in f.items() if k2 != "evaluation"}
            init = torch.as_tensor(f["z"])
        judge, key = (self.evaluate_noise, "noise") if method == "dp_noise" else (self.evaluate_latent, "latent")
        # Without confirmation a search's first b rollouts are what a search of budget b spends (one search gives
        # the curve); with it, a smaller budget confirms fewer challengers, so each budget runs its own search.
        if self.confirm_rollouts:
            picks = []
            for b in budgets:
                res, times = self.search(method, b, init)
                picks.append((b, res, res.best_trace[-1][1], res.rollouts_used, res.seconds))
        else:
            res, times = self.search(method, max(budgets), init)
            picks = [(b, res, i, n, times[n - 1]) for b, n, i in best_so_far(res, budgets)]
        # the search of the largest budget (the only one without confirmation); with it (settings' confirm_rollouts)
        # every budget's own search is summed too
        rec["search"] = {"method": "cma", "budget": max(budgets), "seconds": round(res.seconds, 2),
                         "candidates": len(res.history), "rollouts_used": res.rollouts_used,
                         "popsize": default_popsize(res.history[0].latent.numel())}
        if self.confirm_rollouts:
            rec["search"]["seconds_all_budgets"] = round(sum(p[1].seconds for p in picks), 2)
        judged: dict[tuple, dict[str, Any]] = {}
        rec["points"] = []
        for b, res_b, i, n, seconds in picks:
            c = res_b.history[i]
            x = tuple(c.latent.reshape(-1).tolist())
            if x not in judged:
                judged[x] = judge(c.latent)
            rec["points"].append({"budget": b, "rollouts_used": n, "seconds": round(seconds, 2),
                                  "candidate": i, "generation": c.generation, "search_score": c.score,
                                  "search_success": c.success, "search_rollouts": c.rollouts,
                                  "norm": float(c.latent.norm()), key: c.latent.tolist(), **judged[x]})
        return rec


def _factory(suite: Any, scene: int | str) -> EnvFactory:
    """One env of ``scene`` as the protocol's rollouts make it (``rollouts.make_vector_env``)."""
    import gymnasium as gym

    return functools.partial(gym.make, suite.gym_id, scene=scene, max_episode_steps=suite.max_episode_steps,
                             disable_env_checker=True, **suite.camera_kwargs)


# ----------------------------------------------------------------------------- the table and the curve


def _groups(book: dict[str, Any]) -> dict[tuple, dict[str, dict[str, Any]]]:
    """Records per (env, scene, seed, score), each group's methods in :data:`METHODS` order."""
    groups: dict[tuple, dict[str, dict[str, Any]]] = {}
    for rec in book["records"].values():
        groups.setdefault((rec["env"], str(rec["scene"]), rec["seed"], rec["score"]), {})[rec["method"]] = rec
    return {g: {m: ms[m] for m in METHODS if m in ms} for g, ms in sorted(groups.items(), key=lambda kv: str(kv[0]))}


def curves_markdown(book: dict[str, Any]) -> str:
    """One table per (env, scene, seed, score): success over the evaluation rollouts of the best candidate so far
    at each budget, and the search's wall time at its largest budget."""
    lines = ["# Search curves", "",
             "Success over the evaluation rollouts (the protocol's seeds for the scene) of each search's best "
             "candidate after the first b rollouts (in brackets, in tables scored by way-points: their mean progress "
             "through the way-points); the search's own rollouts reset on other seeds. search s: the search's wall time at "
             "its largest budget; fit s: the gradient fit's (z_fit searches after it). Wall time on "
             f"{book.get('cpu', 'an unrecorded CPU')}, {book.get('threads', '?')} torch thread(s).", ""]
    for (env, scene, seed, score), recs in _groups(book).items():
        budgets = sorted({p["budget"] for r in recs.values() for p in r["points"] if p["budget"] > 0})
        any_rec = next(iter(recs.values()))["settings"]
        lines += [f"## {env} {_scene_name(scene)}, seed {seed}, scored by {score}", "",
                  f"{any_rec['rollouts']} evaluation rollouts (seeds {any_rec['evaluation_seeds'][0]}.."
                  f"{any_rec['evaluation_seeds'][1]}); {any_rec['rollouts_per_candidate']} search rollouts per "
                  f"candidate (seeds {any_rec['search_seeds'][0]}..{any_rec['search_seeds'][1]}).", "",
                  "| method | " + " | ".join(["fit", *map(str, budgets)]) + " | search s | fit s |",
                  "|---" * (len(budgets) + 4) + "|"]
        for method, rec in recs.items():
            by_budget = {p["budget"]: p for p in rec["points"]}
            cells = [_cell(by_budget[b]) if b in by_budget else "" for b in [0, *budgets]]
            search_s = f"{rec['search']['seconds']:.1f}" if "search" in rec else ""
            fit_s = f"{rec['fit']['seconds']:.1f}" if "fit" in rec else ""
            lines.append(f"| {method} | " + " | ".join(cells) + f" | {search_s} | {fit_s} |")
        commands = sorted({r["command"] for r in recs.values() if r.get("command")})
        if commands:
            lines += ["", *[f"`{c}`" for c in commands]]
        lines.append("")
    return "\n".join(lines)


def _cell(point: dict[str, Any]) -> str:
    wp = point.get("waypoint_score")
    return f"{100 * point['success']:.1f} %" + ("" if wp is None else f" ({wp:.2f})")


def draw_curves(book: dict[str, Any], path: Path) -> None:
    """Success against rollouts used (log2), one line per search, the fit as a horizontal line; a panel per
    (env, scene, seed, score)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    groups = _groups(book)
    fig, axes = plt.subplots(1, max(1, len(groups)), figsize=(5.5 * max(1, len(groups)), 4.2), squeeze=False)
    for ax, ((env, scene, seed, score), recs) in zip(axes[0], groups.items(), strict=False):
        for method, rec in recs.items():
            pts = rec["points"]
            if method == "fit":
                ax.axhline(pts[0]["success"], color="black", ls="--", lw=1.2, label=LABELS[method])
                continue
            x = [max(p["rollouts_used"], 1) for p in pts]
            y = np.array([p["success"] for p in pts])
            err = np.sqrt(y * (1 - y) / np.array([p["n"] for p in pts]))
            ax.errorbar(x, y, yerr=err, marker="o", ms=4, capsize=2, label=LABELS[method], color=COLORS.get(method))
        ax.set_xscale("log", base=2)
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("search rollouts used")
        ax.set_ylabel("success (evaluation rollouts)")
        ax.set_title(f"{env} {_scene_name(scene)}, seed {seed}, score {score}", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    write_figure_atomic(fig, path, dpi=110)
    plt.close(fig)


def write_records(book: dict[str, Any], dest: Path) -> None:
    """The record, its table and its figure, each whole or not at all (figure and table first: the record
    names only what they show)."""
    write_text_atomic(dest / TABLE, curves_markdown(book))
    draw_curves(book, dest / FIGURE)
    write_text_atomic(dest / RECORD, json.dumps(book, indent=1))
