"""Search the latent z by outcome: black-box optimisation of what the rollouts achieve, no demonstration needed.

A fit (``fit_latent``) finds the z whose actions look like one demonstration; that z need not be the one that
succeeds (docs/experiments.md, latent landscapes), and without a demonstration there is nothing to fit. Here z
is scored by rolling the policy out under it: task success, a summed reward, or way-points passed in order
(:mod:`~lerobot_pdp.outcome_scores`). The latent is small (2-D on every benchmark env; one z per phase for
gripper-segmented policies, [M, d_z]), so a derivative-free search over it is cheap: CMA-ES (the ``cma``
package) or the cross-entropy method, a population per step rolled out together in one vector env
(:mod:`~lerobot_pdp.candidate_rollouts`).

The budget counts rollouts. The starting points are scored first (the mode means, or a given latent such as a
fit's), so the search never returns worse than where it started, as measured. Same seed, same history; Ctrl-C
returns the best so far, marked interrupted; a rollout or score failing after the first candidate raises
:class:`LatentSearchError` carrying the search so far (at the first, the error itself: nothing to keep).
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from .candidate_rollouts import CandidateRollouts, EnvFactory
from .console import latent_text
from .outcome_scores import Outcome, Score, WaypointScore, resolve_score
from .search_defaults import CONFIRM_ROLLOUTS
from .steering_state import as_latent_tensor

logger = logging.getLogger(__name__)

METHODS = ("cma", "cem")
CEM_ELITE_FRACTION = 0.25
CEM_SMOOTHING = 0.7  # share of the elites' statistics in each CEM update (the rest: the previous ones)


@dataclass
class Candidate:
    """One latent tried: its rollouts' mean score and success rate."""

    latent: Tensor  # [d_z] or [M, d_z], the shape of the starting point
    score: float
    success: float
    rollouts: int
    generation: int  # 0: a starting point; 1, 2, ...: the optimiser's populations
    scores: list[float] = field(default_factory=list)  # per rollout
    successes: list[float] = field(default_factory=list)  # per rollout, 0 or 1

    def to_dict(self) -> dict[str, Any]:
        return {"latent": self.latent.tolist(), "score": self.score, "success": self.success,
                "rollouts": self.rollouts, "generation": self.generation, "scores": self.scores,
                "successes": self.successes}


@dataclass
class SearchResult:
    """The best latent found, its score and success rate, and every candidate in the order tried."""

    latent: Tensor | None
    score: float
    success: float
    history: list[Candidate]
    method: str
    seed: int
    budget: int
    rollouts_per_candidate: int
    objective: Any  # the score's name, or its settings (way-points, radius)
    interrupted: bool = False
    seconds: float = 0.0
    confirm_rollouts: int = 0
    # (rollouts used, index into history of the best so far) each time the best changed: what the search would
    # have returned had its budget ended there
    best_trace: list[tuple[int, int]] = field(default_factory=list)

    @property
    def rollouts_used(self) -> int:
        return sum(c.rollouts for c in self.history)

    def __repr__(self) -> str:  # a summary: the dataclass's would print every candidate (to_dict() holds them)
        latent = None if self.latent is None else latent_text(self.latent)
        return (f"SearchResult(latent={latent}, score={self.score:.4g}, success={self.success:.3g}, "
                f"{len(self.history)} candidates, {self.rollouts_used} of {self.budget} rollouts, method={self.method!r}, "
                f"objective={self.objective!r}{', interrupted' if self.interrupted else ''}, seconds={self.seconds:.1f})")

    def to_dict(self) -> dict[str, Any]:
        return {"latent": None if self.latent is None else self.latent.tolist(), "score": self.score,
                "success": self.success, "method": self.method, "seed": self.seed, "budget": self.budget,
                "rollouts_per_candidate": self.rollouts_per_candidate, "confirm_rollouts": self.confirm_rollouts,
                "rollouts_used": self.rollouts_used, "objective": self.objective, "interrupted": self.interrupted,
                "seconds": round(self.seconds, 1), "best_trace": [list(t) for t in self.best_trace],
                "history": [c.to_dict() for c in self.history]}

    def best_at(self, rollouts: int) -> int | None:
        """Index into ``history`` of what the search would have returned after its first ``rollouts`` rollouts."""
        best = None
        for used, i in self.best_trace:
            if used > rollouts:
                break
            best = i
        return best


class LatentSearchError(RuntimeError):
    """A rollout or the score failed after the first candidate; ``result`` holds the search up to the candidates
    before it (a failure at the first candidate raises its own error: a setup error, most often)."""

    def __init__(self, message: str, result: SearchResult):
        super().__init__(message)
        self.result = result


def search_latent(policy: Any, env_factory: EnvFactory, score: str | Score = "success", budget: int = 200,
                  init: Any = "modes", method: str = "cma", seed: int = 0, rollouts_per_candidate: int = 2,
                  sigma: float | None = None, popsize: int | None = None, max_envs: int = 16,
                  processors: tuple | None = None, env_processors: tuple | None = None,
                  confirm_rollouts: int = CONFIRM_ROLLOUTS, progress: bool = True) -> SearchResult:
    """Search ``policy``'s latent for the best mean ``score`` over rollouts in envs made by ``env_factory``.

    Args:
        env_factory: makes one env (``gym.make(id, ..., max_episode_steps=...)``); LeRobot's key mapping
            (``agent_pos`` -> ``observation.state``, ...) must give the checkpoint's features.
        score: ``"success"``, ``"reward"`` (summed), a :class:`~lerobot_pdp.outcome_scores.WaypointScore` or any
            ``Callable[[Outcome], float]``; higher is better.
        budget: rollouts in all; each candidate costs ``rollouts_per_candidate``.
        init: ``"modes"`` (start from every mode's mean latent, then search from the best), a latent ([d_z] or
            [M, d_z]), or a fit result (its ``z``).
        method: ``"cma"`` (CMA-ES) or ``"cem"`` (cross-entropy method).
        sigma: initial step size (default: half the spread of the training latents, their RMS std per dim).
        popsize: candidates per population (default CMA-ES's, 4 + 3 ln D).
        max_envs: sub-envs per vector env (candidates are batched up to it).
        processors: the policy's (pre, post) processors (default: built from the policy's own statistics, as
            ``lerobot-train`` saves them).
        env_processors: LeRobot's env (pre, post) processors (default: none).
        confirm_rollouts: a candidate that beats the best so far is rolled out again up to this many rollouts in
            all, and replaces it only if still better (0: no confirmation, the best of ``rollouts_per_candidate``).
    """
    if not callable(env_factory):  # an env, or a gym id: the search makes up to max_envs envs of its own
        raise TypeError(f"env_factory must make one new env per call, e.g. functools.partial(gym.make, "
                        f"'lerobot_pdp/ReachAround-v0', scene=3, max_episode_steps=300); got {type(env_factory).__name__}"
                        f" {env_factory!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    for name, value, low in (("budget", budget, 1), ("rollouts_per_candidate", rollouts_per_candidate, 1),
                             ("max_envs", max_envs, 1), ("popsize", 2 if popsize is None else popsize, 2),
                             ("confirm_rollouts", confirm_rollouts, 0), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if budget < rollouts_per_candidate:
        raise ValueError(f"budget {budget} rollouts cannot pay for one candidate of {rollouts_per_candidate} "
                         "rollouts (rollouts_per_candidate)")
    if 0 < confirm_rollouts <= rollouts_per_candidate:
        raise ValueError(f"confirm_rollouts must be 0 (off) or more than rollouts_per_candidate "
                         f"({rollouts_per_candidate}), got {confirm_rollouts}")
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a finite number > 0, got {sigma!r}")
    score_fn, objective = resolve_score(score)
    if isinstance(score_fn, WaypointScore):  # before any rollout: points the agent can never pass
        probe = env_factory()
        try:
            score_fn.check_env(probe)
        finally:
            probe.close()
    starts = start_latents(policy, init)
    if budget // rollouts_per_candidate < len(starts):  # the starts are scored in order, as the budget pays for them
        logger.warning("latent search: budget %d pays for %d of the %d starting latents (%d rollouts each): the last %d "
                       "are not tried and no search step is taken; give budget >= %d to score every start and search "
                       "beyond them", budget, budget // rollouts_per_candidate, len(starts), rollouts_per_candidate,
                       len(starts) - budget // rollouts_per_candidate, len(starts) * rollouts_per_candidate
                       + max(rollouts_per_candidate, confirm_rollouts))
    if processors is None:
        from .processor_pdp import make_pdp_pre_post_processors

        processors = make_pdp_pre_post_processors(policy.config, policy.stats.as_dict())

    k = rollouts_per_candidate
    result = SearchResult(None, -math.inf, 0.0, [], method, seed, budget, k, objective,
                          confirm_rollouts=confirm_rollouts)
    t0 = time.perf_counter()
    bar = tqdm(total=budget // k * k, unit="rollout", desc=f"latent search ({method})", disable=not progress)
    run = CandidateRollouts(policy, env_factory, k, seed, processors, env_processors, max_envs)

    def optimiser_at(best: Tensor) -> Any:  # from the best start, in its shape (one z per phase)
        spread, bounds = latent_geometry(policy, best.reshape(-1).double().numpy(), best.shape)
        return make_optimizer(method, best.reshape(-1).double().numpy(), sigma or 0.5 * spread, popsize, bounds, seed)

    try:
        optimise(result, run, starts, optimiser_at, lambda o, z, i: _score(score_fn, o, z, i), budget, bar)
    except KeyboardInterrupt:
        if not result.history:
            raise
        result.interrupted = True
        if result.latent is None:  # stopped before any best was confirmed: the best scored so far
            result.best_trace.append((result.rollouts_used, max(range(len(result.history)), key=lambda i: (
                result.history[i].score, result.history[i].success, -i))))
            c = result.history[result.best_trace[-1][1]]
            result.latent, result.score, result.success = c.latent, c.score, c.success
    except Exception as e:
        if not result.history:  # nothing to keep: the error as it is (e.g. an env that does not fit the policy)
            raise
        result.seconds = time.perf_counter() - t0
        raise LatentSearchError(f"latent search stopped after {len(result.history)} candidates "
                                f"({result.rollouts_used} rollouts): {e}", result) from e
    finally:
        bar.close()
        run.close()
    result.seconds = time.perf_counter() - t0
    if len(result.history) > 1 and len({c.score for c in result.history}) == 1:  # its "best" is the first tried
        logger.warning("latent search: every candidate scored %.3g, so the search had nothing to follow and the best "
                       "latent is just the first one tried; score by way-points (WaypointScore, or --waypoints) to "
                       "reward partial progress, or give a larger budget", result.score)
    return result


def optimise(result: SearchResult, run: Callable[..., list[list[Outcome]]], starts: list[Tensor],
             optimiser_at: Callable[[Tensor], Any], score: Callable[[Outcome, Tensor, int], float], budget: int,
             bar: Any) -> None:
    """The search loop, whatever is searched (a latent here, the benchmark's DP noise): score ``starts``, then
    ask / tell the optimiser ``optimiser_at(best start)`` while ``budget`` rollouts pay for a candidate, each
    candidate scored by the mean of ``score(outcome, candidate, index)`` over its rollouts (``run(xs, first,
    count)``). With ``result.confirm_rollouts`` C > ``rollouts_per_candidate`` k, a candidate that beats the best
    on its k rollouts is rolled out on C - k more seeds and replaces it only if it is still better over all C
    (a best picked from k noisy rollouts is mostly luck); the budget pays for those too. Fills ``result`` as it
    goes, so an interruption keeps what was tried."""
    k = result.rollouts_per_candidate
    extra = max(result.confirm_rollouts - k, 0)

    def key(c: Candidate) -> tuple[float, float]:
        return c.score, c.success

    def best() -> Candidate | None:
        return result.history[result.best_trace[-1][1]] if result.best_trace else None

    def promote(i: int, used: int) -> None:
        c = result.history[i]
        result.latent, result.score, result.success = c.latent, c.score, c.success
        result.best_trace.append((used, i))
        bar.set_postfix(best=f"{result.score:.3g}", success=f"{result.success:.0%}")

    def confirm(i: int) -> None:
        """Roll candidate ``i`` out on ``extra`` more seeds: its score and success become the means of all."""
        c = result.history[i]
        (outcomes,) = run([c.latent], k, extra)
        values = [score(o, c.latent, i) for o in outcomes]  # all scored before any is kept: an interruption
        c.scores, c.successes = c.scores + values, c.successes + [float(o.success) for o in outcomes]  # keeps k
        c.score, c.success, c.rollouts = float(np.mean(c.scores)), float(np.mean(c.successes)), len(c.scores)
        bar.update(extra)

    def evaluate(xs: list[Tensor], generation: int) -> list[float]:
        first = len(result.history)
        for x, outcomes in zip(xs, run(xs), strict=True):
            values = [score(o, x, len(result.history)) for o in outcomes]
            successes = [float(o.success) for o in outcomes]
            result.history.append(Candidate(x, float(np.mean(values)), float(np.mean(successes)), k, generation,
                                            values, successes))
            bar.update(k)
            b = best()
            if not extra and (b is None or key(result.history[-1]) > key(b)):  # in order: what a budget ending
                promote(len(result.history) - 1, result.rollouts_used)  # after this candidate returns
        new = list(range(first, len(result.history)))
        means = [result.history[i].score for i in new]  # what the optimiser is told: every candidate on k rollouts
        if not extra:
            return means
        pending = list(new)
        while pending:  # the most promising challenger first; each one promoted raises the bar for the rest
            b = best()
            pending = [i for i in pending if b is None or key(result.history[i]) > key(b)]
            if not pending:
                break
            i = max(pending, key=lambda j: (key(result.history[j]), -j))  # the best, the first of equals
            pending.remove(i)
            if result.rollouts_used + extra <= budget:
                confirm(i)
            elif b is not None:
                continue  # the budget cannot confirm it: the confirmed best stays
            if b is None or key(result.history[i]) > key(b):
                promote(i, result.rollouts_used)
        return means

    evaluate(starts[:budget // k], 0)
    shape = result.latent.shape
    opt = optimiser_at(result.latent)
    generation = 1
    # with confirmation, a candidate the budget cannot confirm cannot replace the best: no rollouts spent on it
    while budget - result.rollouts_used >= k + extra:
        x = opt.ask()
        n = min(len(x), (budget - result.rollouts_used) // k)
        means = evaluate([torch.as_tensor(v, dtype=torch.float32).reshape(shape) for v in x[:n]], generation)
        if n == len(x):
            opt.tell(x, np.asarray(means))
        generation += 1


def _score(score_fn: Score, outcome: Outcome, z: Tensor, index: int) -> float:
    try:
        value = float(score_fn(outcome))
    except Exception as e:
        raise ValueError(f"the score {getattr(score_fn, '__name__', type(score_fn).__name__)} raised "
                         f"{type(e).__name__}: {e} (candidate {index}, latent {z.tolist()})") from e
    if not math.isfinite(value):
        raise ValueError(f"the score returned {value} for candidate {index} (latent {z.tolist()}): expected a "
                         "finite number")
    return value


def start_latents(policy: Any, init: Any) -> list[Tensor]:
    """The starting latents of ``init``: the mode means in mode order, a given latent, or a fit's ``z``."""
    if isinstance(init, str):
        if init != "modes":
            raise ValueError(f"init must be 'modes', a latent or a fit result, got {init!r}")
        modes = policy.mode_latents()
        return [modes[m].float() for m in sorted(modes)]
    z = as_latent_tensor(getattr(init, "z", init)).detach().cpu()
    d = policy.config.latent_dim
    if z.dim() not in (1, 2) or z.shape[-1] != d or z.numel() == 0:
        raise ValueError(f"init latent must have shape [{d}] or [M, {d}] (one per phase), got {tuple(z.shape)}")
    if not bool(torch.isfinite(z).all()):
        raise ValueError(f"init latent has non-finite values: {z.tolist()}")
    return [z]


def latent_geometry(policy: Any, x0: np.ndarray, shape: torch.Size) -> tuple[float, list | None]:
    """The training latents' spread (RMS std per dim; 1 = the prior's without behaviors) and a search box: their
    range widened by one spread on each side (and around ``x0``), per phase. The policy was never trained far
    outside them."""
    if len(policy.model.bank.traces) < 2:
        return 1.0, None
    with torch.no_grad():
        train = policy.behavior_latents().double().cpu().numpy()
    spread = float(np.sqrt(train.var(0).mean()))
    if not spread > 0:
        return 1.0, None
    phases = int(np.prod(shape)) // train.shape[1]
    low = np.minimum(np.tile(train.min(0), phases), x0) - spread
    high = np.maximum(np.tile(train.max(0), phases), x0) + spread
    return spread, [low.tolist(), high.tolist()]


def search_provenance(result: SearchResult) -> dict[str, Any]:
    """Where a searched latent came from, as an adapted checkpoint keeps it (``adaptation.json``)."""
    return {"source": "search", "method": result.method, "objective": result.objective, "score": result.score,
            "success": result.success, "budget": result.budget, "rollouts_used": result.rollouts_used,
            "rollouts_per_candidate": result.rollouts_per_candidate, "confirm_rollouts": result.confirm_rollouts,
            "candidates": len(result.history),
            "seed": result.seed, "interrupted": result.interrupted,
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}


def default_popsize(dim: int) -> int:
    return 4 + int(3 * math.log(dim))


def make_optimizer(method: str, x0: np.ndarray, sigma: float, popsize: int | None = None, bounds: list | None = None,
                   seed: int = 0) -> CMAES | CrossEntropy:
    """An ask/tell maximiser over flat vectors: ``ask()`` -> [popsize, D], ``tell(x, scores)``."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return (CMAES if method == "cma" else CrossEntropy)(np.asarray(x0, dtype=float), sigma, popsize, bounds, seed)


class CMAES:
    """CMA-ES maximising the score, on its own numpy random state (``cma`` draws from numpy's global one)."""

    def __init__(self, x0: np.ndarray, sigma: float, popsize: int | None, bounds: list | None, seed: int):
        import cma

        self._state: Any = None
        opts = {"seed": seed + 1,  # cma reads 0 as "seed from the clock"
                "popsize": popsize or default_popsize(len(x0)), "bounds": bounds or [None, None], "verbose": -9}
        with self._own_random():
            self.es = cma.CMAEvolutionStrategy(x0, sigma, opts)

    @contextlib.contextmanager
    def _own_random(self) -> Iterator[None]:
        outer = np.random.get_state()
        if self._state is not None:
            np.random.set_state(self._state)
        try:
            yield
        finally:
            self._state = np.random.get_state()
            np.random.set_state(outer)

    def ask(self) -> np.ndarray:
        with self._own_random():
            return np.asarray(self.es.ask())

    def tell(self, x: np.ndarray, scores: np.ndarray) -> None:
        with self._own_random():
            self.es.tell(list(x), list(-scores))  # cma minimises


class CrossEntropy:
    """The cross-entropy method: a diagonal Gaussian refitted to the best quarter of each population."""

    def __init__(self, x0: np.ndarray, sigma: float, popsize: int | None, bounds: list | None, seed: int):
        self.mean, self.std = x0.copy(), np.full(len(x0), float(sigma))
        self.min_std = 0.05 * float(sigma)  # the population never collapses onto one point
        self.popsize = popsize or default_popsize(len(x0))
        self.bounds = None if bounds is None else (np.asarray(bounds[0]), np.asarray(bounds[1]))
        self.rng = np.random.default_rng(seed)

    def ask(self) -> np.ndarray:
        x = self.mean + self.std * self.rng.standard_normal((self.popsize, len(self.mean)))
        return x if self.bounds is None else np.clip(x, *self.bounds)

    def tell(self, x: np.ndarray, scores: np.ndarray) -> None:
        n_elite = min(len(x), max(2, round(CEM_ELITE_FRACTION * len(x))))
        elite = x[np.argsort(-scores, kind="stable")[:n_elite]]
        a = CEM_SMOOTHING
        self.mean = a * elite.mean(0) + (1 - a) * self.mean
        self.std = np.maximum(a * elite.std(0) + (1 - a) * self.std, self.min_std)
