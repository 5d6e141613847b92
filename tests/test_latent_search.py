"""Search by outcome: z searched with CMA-ES / CEM over rollouts of a real suite env through LeRobot's rollout loop,
scored by success, reward or way-points; deterministic, within budget, interruptible; ``lerobot-pdp search``
writing an adapted checkpoint; bad input named.

The policy is small and untrained, with its FiLM layers drawn at random (training starts them at the identity,
where z changes nothing) so that different latents act differently. These tests check the machinery, not that
a search finds success: that needs a trained checkpoint (docs/deploy.md, "Search by outcome").
"""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from policies import saved_steerable_checkpoint

from lerobot_pdp import PDPPolicy
from lerobot_pdp.candidate_rollouts import CandidateRollouts, PerEnvLatents
from lerobot_pdp.checkpoint import ADAPTATION_INFO
from lerobot_pdp.cli import main as cli
from lerobot_pdp.latent_search import LatentSearchError, SearchResult, make_optimizer, optimise, search_latent
from lerobot_pdp.outcome_scores import Outcome, WaypointScore, waypoint_progress

SCENE3_WAYPOINTS = [[0.0, -0.30, 0.40], [0.19, -0.12, 0.59], [0.19, 0.12, 0.59], [0.0, 0.30, 0.40]]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A small untrained PDP with reach-around's features and random FiLM layers, saved as lerobot-train saves
    one (weights + processors)."""
    return saved_steerable_checkpoint(tmp_path_factory.mktemp("search"))[0]


@pytest.fixture
def policy(checkpoint) -> PDPPolicy:
    p = PDPPolicy.from_pretrained(checkpoint)
    p.eval()
    return p


def short_env(scene=0, steps: int = 30, name: str = "reach-around"):
    """A suite env cut to ``steps`` steps: the search's machinery in a fraction of an episode's time."""
    import lerobot_pdp.envs as envs

    suite = envs.get_suite_env(name)
    return lambda: gym.make(suite.gym_id, scene=scene, max_episode_steps=steps, disable_env_checker=True)


def history(res) -> list:
    return [(c.latent.tolist(), c.scores, c.success, c.generation) for c in res.history]


# ------------------------------------------------------------------------------------------------ scores


def test_waypoint_progress_on_hand_made_paths():
    w = np.array([[0.0, 0.0], [1.0, 0.0]])
    line = np.linspace([0.0, 0.0], [1.0, 0.0], 11)
    assert waypoint_progress(line, w, 0.05) == 1.0
    # backwards: the second way-point comes first, so only the first counts; the rest of the path is at 1 m
    assert waypoint_progress(line[::-1], w, 0.05) == pytest.approx((1 + 0.05 / 1.0) / 2)
    # none passed: the closest approach to the first gives the partial credit
    far = np.array([[0.0, 0.2], [1.0, 0.2]])
    assert waypoint_progress(far, w, 0.05) == pytest.approx(0.05 / 0.2 / 2)
    # closer scores higher, and passing one more always beats coming close to it
    near = np.array([[0.0, 0.1], [1.0, 0.1]])
    half = np.array([[0.0, 0.0], [0.5, 0.0]])
    assert waypoint_progress(far, w, 0.05) < waypoint_progress(near, w, 0.05) < 0.5 <= waypoint_progress(half, w, 0.05)
    # a point exactly at the radius is passed; in order means after the previous pass, not before
    assert waypoint_progress(np.array([[0.05, 0.0], [1.0, 0.05]]), w, 0.05) == 1.0
    assert waypoint_progress(np.array([[1.0, 0.0], [0.0, 0.0]]), w, 0.05) == pytest.approx((1 + 0.05) / 2)
    with pytest.raises(ValueError, match=r"path must be \[T, 2\]"):
        waypoint_progress(np.zeros((5, 3)), w, 0.05)
    with pytest.raises(ValueError, match="radius must be > 0"):
        waypoint_progress(line, w, 0.0)


def test_waypoint_score_reads_the_agents_positions():
    states = np.c_[np.linspace([0.0, -0.3, 0.4], [0.0, 0.3, 0.4], 20), np.ones((20, 3))]  # positions, velocities
    score = WaypointScore([[0.0, -0.3, 0.4], [0.0, 0.3, 0.4]], radius=0.02)
    assert score(Outcome(False, 0.0, states)) == 1.0
    assert WaypointScore([[1.0, 1.0]], 0.02, dims=[3, 4])(Outcome(False, 0.0, states)) == 1.0  # the velocity dims
    with pytest.raises(ValueError, match="agent_pos"):
        score(Outcome(False, 0.0, np.zeros((0, 0))))
    assert "finish" not in score.describe()  # the provenance of searches made before the option is unchanged
    for bad, match in ((([[0.0, np.nan, 0.0]], 0.05), "finite"), (([[0.0, 0.0, 0.0]], -1.0), "radius"),
                       (([], 0.05), "non-empty")):
        with pytest.raises(ValueError, match=match):
            WaypointScore(*bad)


def test_the_finish_score_adds_the_tasks_success_only_after_every_way_point():
    """waypoints then success: 2 = passed all and succeeded, 1 = passed all and failed; a success that skipped a
    way-point earns nothing more than its progress (the route is what the user asked for)."""
    states = np.c_[np.linspace([0.0, -0.3, 0.4], [0.0, 0.3, 0.4], 20), np.ones((20, 3))]
    points = [[0.0, -0.3, 0.4], [0.0, 0.3, 0.4]]
    finish = WaypointScore(points, radius=0.02, finish=True)
    assert finish(Outcome(True, 0.0, states)) == 2.0
    assert finish(Outcome(False, 0.0, states)) == 1.0
    short = states[:10]  # stops half way: the second way-point is 0.3 m off
    assert finish(Outcome(True, 0.0, short)) == WaypointScore(points, radius=0.02)(Outcome(True, 0.0, short)) < 1.0
    assert WaypointScore(points, radius=0.02)(Outcome(True, 0.0, states)) == 1.0  # without finish: progress only
    assert finish.describe()["finish"] is True


@pytest.mark.parametrize("method", ["cma", "cem"])
def test_optimizers_climb_to_the_best_point_and_repeat_under_a_seed(method):
    target = np.array([0.7, -0.4, 0.2, 0.1])

    def run(seed):
        opt, asked = make_optimizer(method, np.zeros(4), 0.5, bounds=[[-2] * 4, [2] * 4], seed=seed), []
        for _ in range(30):
            x = opt.ask()
            asked.append(x)
            opt.tell(x, -((x - target) ** 2).sum(1))  # maximised
        return np.concatenate(asked)

    x = run(0)
    assert np.linalg.norm(x[-6:].mean(0) - target) < 0.1
    assert np.array_equal(x, run(0)) and not np.array_equal(x, run(1))


# ------------------------------------------------------------------------------------- batched rollouts


def test_each_env_of_a_batch_acts_under_its_own_latent(policy):
    """Three candidates x two rollouts share one vector env: the denoiser gets each env its candidate's z."""
    from lerobot_pdp.processor_pdp import make_pdp_pre_post_processors

    seen: list[torch.Tensor] = []
    generate = policy.generate
    policy.generate = lambda obs, z, *a, **kw: (seen.append(z.clone()), generate(obs, z, *a, **kw))[1]
    policy.set_latent([0.5, 0.5])
    latents = [torch.tensor([0.1, 0.2]), torch.tensor([-1.0, 0.3]), torch.tensor([0.7, -0.7])]
    procs = make_pdp_pre_post_processors(policy.config, policy.stats.as_dict())
    with CandidateRollouts(policy, short_env(steps=12), rollouts=2, seed=0, processors=procs) as run:
        outcomes = run(latents)
    assert [len(o) for o in outcomes] == [2, 2, 2]
    assert len(seen) == 2 and all(torch.equal(z, torch.stack(latents).repeat_interleave(2, 0)) for z in seen)
    o = outcomes[0][0]
    assert o.states.shape == (13, 6) and np.allclose(o.states[0, :3], [0.0, -0.3, 0.4], atol=0.01)
    assert "is_success" in o.info and o.success is False
    assert policy.active_latent.tolist() == [[0.5, 0.5]] and not isinstance(policy.steering, PerEnvLatents)


def test_per_phase_latents_follow_each_envs_phase():
    latents = torch.arange(12.0).reshape(2, 3, 2)  # 2 envs, 3 phases
    s = PerEnvLatents(latents)
    assert s.per_phase
    s.phases.phases(2, "cpu")
    s.phases.phase = torch.tensor([0, 2])
    assert s.latent_for(2, "cpu", None).tolist() == [latents[0, 0].tolist(), latents[1, 2].tolist()]
    with pytest.raises(RuntimeError, match="3 envs for 2 candidate"):
        s.latent_for(3, "cpu", None)


# ----------------------------------------------------------------------------------------------- search


@pytest.mark.parametrize("method", ["cma", "cem"])
def test_search_is_deterministic_within_budget_and_keeps_every_candidate(policy, method):
    score = WaypointScore(SCENE3_WAYPOINTS, 0.05)
    kw = {"budget": 21, "rollouts_per_candidate": 2, "method": method, "max_envs": 8, "progress": False,
          "confirm_rollouts": 0}
    a = search_latent(policy, short_env(scene=3), score, seed=4, **kw)
    assert len(a.history) == 10 and a.rollouts_used == 20 <= a.budget  # a last odd rollout buys no candidate
    assert [c.generation for c in a.history] == [0] * 8 + [1, 1]  # the 8 mode means first
    assert all(c.rollouts == 2 and len(c.scores) == 2 and c.score == pytest.approx(np.mean(c.scores))
               for c in a.history)
    best = max(a.history, key=lambda c: (c.score, c.success))
    assert torch.equal(a.latent, best.latent) and a.score == best.score and not a.interrupted
    assert len({tuple(c.latent.tolist()) for c in a.history}) == 10 and len({c.score for c in a.history}) > 1
    b = search_latent(policy, short_env(scene=3), score, seed=4, **kw)
    assert history(a) == history(b)
    c = search_latent(policy, short_env(scene=3), score, seed=5, **kw)
    assert history(c)[8:] != history(a)[8:]
    assert json.loads(json.dumps(a.to_dict()))["rollouts_used"] == 20


class _Bar:
    def update(self, n):
        pass

    def set_postfix(self, **kw):
        pass


def _lucky_and_steady(confirm: int) -> SearchResult:
    """Two starts: "lucky" succeeds on its first two seeds only, "steady" on three seeds in four."""
    def run(xs, first=0, count=2):
        out = []
        for x in xs:
            lucky = bool(x[0] == 0)
            out.append([Outcome(success=(j < 2) if lucky else (j % 4 != 3), reward=0.0, states=np.zeros((0, 0)),
                                info={}) for j in range(first, first + count)])
        return out

    budget = 12 if confirm else 4  # the two starts (and their confirmation): no optimiser step
    res = SearchResult(None, -np.inf, 0.0, [], "cma", 0, budget, 2, "success", confirm_rollouts=confirm)
    optimise(res, run, [torch.zeros(1), torch.ones(1)], lambda x0: None, lambda o, x, i: float(o.success), budget,
             _Bar())
    return res


def test_confirmation_keeps_a_lucky_candidate_from_becoming_the_best():
    plain = _lucky_and_steady(0)  # on two rollouts each, both score 1.0: the first of equals wins
    assert plain.latent.tolist() == [0.0] and plain.best_trace == [(2, 0)] and plain.rollouts_used == 4
    confirmed = _lucky_and_steady(6)  # each re-rolled to six seeds: lucky 2/6, steady 5/6
    assert confirmed.latent.tolist() == [1.0] and confirmed.success == pytest.approx(5 / 6)
    assert [c.rollouts for c in confirmed.history] == [6, 6] and confirmed.rollouts_used == 12
    assert confirmed.history[0].scores == [1, 1, 0, 0, 0, 0] and confirmed.best_trace == [(8, 0), (12, 1)]
    assert confirmed.best_at(7) is None and confirmed.best_at(8) == 0 and confirmed.best_at(100) == 1


def test_confirmed_search_is_deterministic_and_its_best_the_best_confirmed(policy):
    score = WaypointScore(SCENE3_WAYPOINTS, 0.05)
    kw = {"budget": 30, "rollouts_per_candidate": 2, "confirm_rollouts": 4, "max_envs": 8, "progress": False}
    a = search_latent(policy, short_env(scene=3), score, seed=4, **kw)
    assert a.rollouts_used <= 30 and {c.rollouts for c in a.history} <= {2, 4}
    confirmed = [c for c in a.history if c.rollouts == 4]
    assert confirmed and all(a.history[i].rollouts == 4 for _, i in a.best_trace)
    assert a.score == max(c.score for c in confirmed) and len(a.history[a.best_trace[-1][1]].scores) == 4
    assert history(a) == history(search_latent(policy, short_env(scene=3), score, seed=4, **kw))
    assert json.loads(json.dumps(a.to_dict()))["confirm_rollouts"] == 4


def test_search_from_a_latent_or_a_fit(policy, checkpoint):
    z0 = torch.tensor([0.3, -0.2])
    res = search_latent(policy, short_env(), "reward", budget=6, init=z0, rollouts_per_candidate=2, confirm_rollouts=0,
                        progress=False)
    assert torch.equal(res.history[0].latent, z0) and [c.generation for c in res.history] == [0, 1, 1]
    assert res.objective == "reward"
    data = checkpoint.parent / "data"
    fit = policy.fit_latent((data, 0), steps=1, activate=False)
    res = search_latent(policy, short_env(), "success", budget=2, init=fit, rollouts_per_candidate=1,
                        confirm_rollouts=0, progress=False)
    assert torch.equal(res.history[0].latent, fit.z) and res.rollouts_used == 2


def test_ctrl_c_returns_the_best_so_far_marked_interrupted(policy):
    calls = []

    def score(outcome):
        calls.append(1)
        if len(calls) > 6:
            raise KeyboardInterrupt
        return float(len(calls) == 3)  # the second candidate's first rollout

    res = search_latent(policy, short_env(), score, budget=40, rollouts_per_candidate=2, max_envs=4, confirm_rollouts=0,
                        progress=False)
    assert res.interrupted and len(res.history) == 3 and res.rollouts_used == 6
    assert torch.equal(res.latent, res.history[1].latent) and res.score == 0.5
    said = repr(res)  # a summary, not every candidate
    assert said.startswith("SearchResult(latent=[") and "3 candidates, 6 of 40 rollouts" in said and "interrupted" in said
    from lerobot_pdp.adapted import _search_card_section

    card = _search_card_section({"objective": "success", "env": "avoiding", "date": "today"}, res)
    assert "(cma, 6 rollouts of 40: interrupted, env `avoiding`)" in card  # the card says it stopped short


def test_a_failing_score_keeps_the_search_so_far(policy):
    calls = []

    def flaky(outcome):
        calls.append(1)
        if len(calls) > 4:
            raise RuntimeError("lost the tracker")
        return 0.0

    with pytest.raises(LatentSearchError, match="after 2 candidates.*score flaky raised RuntimeError: lost the "
                       r"tracker \(candidate 2") as e:
        search_latent(policy, short_env(), flaky, budget=20, rollouts_per_candidate=2, max_envs=4, confirm_rollouts=0,
                      progress=False)
    assert len(e.value.result.history) == 2 and e.value.result.rollouts_used == 4
    with pytest.raises(ValueError, match="returned nan for candidate 0"):
        search_latent(policy, short_env(), lambda o: float("nan"), budget=2, rollouts_per_candidate=1,
                      progress=False)


def test_bad_search_arguments_are_named(policy):
    env = short_env()
    for kw, match in (({"budget": 0}, "budget must be an integer >= 1, got 0"),
                      ({"budget": 3, "rollouts_per_candidate": 4}, "budget 3 rollouts cannot pay"),
                      ({"confirm_rollouts": -1}, "confirm_rollouts must be an integer >= 0, got -1"),
                      ({"confirm_rollouts": 2}, r"confirm_rollouts must be 0 \(off\) or more than rollouts_per_candidate "
                       r"\(2\), got 2"),
                      ({"method": "adam"}, "method must be one of"),
                      ({"init": "encoder"}, "init must be 'modes'"),
                      ({"init": torch.zeros(3)}, r"init latent must have shape \[2\]"),
                      ({"score": "distance"}, "score must be one of"),
                      ({"sigma": -1.0}, "sigma must be"),
                      ({"seed": -1}, "seed must be an integer >= 0, got -1")):
        with pytest.raises(ValueError, match=match):
            search_latent(policy, env, **{"budget": 4, "progress": False, **kw})
    with pytest.raises(ValueError, match=r"'observation.state' has shape \(4,\) but the checkpoint was trained on "
                       r"\(6,\)"):
        search_latent(policy, short_env(name="avoiding"), budget=2, progress=False)
    for not_a_factory in (short_env()(), "lerobot_pdp/ReachAround-v0"):  # an env, a gym id: a factory is named
        with pytest.raises(TypeError, match=r"env_factory must make one new env per call, e.g. functools.partial"):
            search_latent(policy, not_a_factory, budget=2, progress=False)
    # way-points the agent can never pass, from Python as on the command line: before any rollout
    for points, match in (([[0.0, 0.0, 5.0]], r"way-point 0 \[0.0, 0.0, 5.0\] lies outside the env's workspace"),
                          ([[0.0, 0.3]], "way-points have 2 coordinates; this env's path has 3")):
        with pytest.raises(ValueError, match=match):
            search_latent(policy, env, WaypointScore(points, radius=0.05), budget=2, progress=False)


def test_policy_search_latent_activates_the_best_and_save_pretrained_keeps_it(policy, tmp_path, caplog):
    with caplog.at_level("WARNING", logger="lerobot_pdp.latent_search"):
        res = policy.search_latent(short_env(), "reward", budget=4, rollouts_per_candidate=1, progress=False)
    n = len(policy.mode_latents())  # a budget short of the starts says which were not tried
    assert f"budget 4 pays for 4 of the {n} starting latents (1 rollouts each): the last {n - 4} are not tried" \
        in caplog.text
    assert torch.equal(policy.active_latent[0], res.latent)
    assert policy.steering.provenance["source"] == "search" and policy.steering.provenance["budget"] == 4
    assert policy.steering.provenance["confirm_rollouts"] == 6  # the default: a best is confirmed before it counts
    policy.save_pretrained(tmp_path / "searched")
    info = json.loads((tmp_path / "searched" / ADAPTATION_INFO).read_text())
    assert info["source"] == "search" and info["rollouts_used"] == 4 and info["objective"] == "reward"
    assert torch.equal(PDPPolicy.from_pretrained(tmp_path / "searched").active_latent[0], res.latent)


# -------------------------------------------------------------------------------------------------- CLI


def test_cli_search_writes_an_adapted_checkpoint_acting_under_the_best(checkpoint, tmp_path, capsys, caplog):
    wps = tmp_path / "wps.json"
    wps.write_text(json.dumps(SCENE3_WAYPOINTS))
    out, hist = tmp_path / "searched", tmp_path / "history.json"
    args = ["search", str(checkpoint), "--env", "reach-around", "--scene", "3", "--waypoints", str(wps), "--budget",
            "3", "--rollouts-per-candidate", "1", "--confirm-rollouts", "0", "--radius", "0.08", "--no-progress"]
    assert cli([*args, "--out", str(out), "--history", str(hist)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed
    assert "the budget ended with the starting latents (3 of them): no cma step was taken" in printed  # 8 modes
    record = json.loads(hist.read_text())
    assert len(record["history"]) == 3 and record["rollouts_used"] == 3
    info = json.loads((out / ADAPTATION_INFO).read_text())
    assert info["source"] == "search" and info["env"] == "reach-around" and info["scene"].startswith("scene 3")
    assert info["objective"]["radius"] == 0.08 and info["objective"]["waypoints"] == SCENE3_WAYPOINTS
    assert info["score"] == record["score"] and info["seed"] == 0 and info["budget"] == 3
    assert info["base_checkpoint"] == str(checkpoint.resolve())
    assert filecmp.cmp(out / "model.safetensors", checkpoint / "model.safetensors", shallow=False)
    assert PDPPolicy.from_pretrained(out).active_latent[0].tolist() == record["latent"]
    card = (out / "README.md").read_text()
    assert card.startswith("# A model card") and "passing 4 way-points in order within 0.08 m" in card

    # an existing --out is refused before anything runs
    assert cli([*args, "--out", str(out)]) == 2
    assert f"--out {out} exists" in capsys.readouterr().err

    # searched again from the latent it carries: the new search replaces the old one, base named as before
    again = tmp_path / "again"
    assert cli(["search", str(out), "--env", "reach-around", "--scene", "3", "--budget", "1",
                "--rollouts-per-candidate", "1", "--init", "adaptation", "--out", str(again), "--no-progress"]) == 0
    info2 = json.loads((again / ADAPTATION_INFO).read_text())
    assert info2["objective"] == "success" and info2["latent"] == [record["latent"]]
    assert info2["base_checkpoint"] == str(checkpoint.resolve())
    card = (again / "README.md").read_text()
    assert card.count("## Adaptation") == 1 and "its score `success`" in card and "way-points" not in card
    # from an adaptation with fitted chunk noises: the search moves the latent alone, and says the noises go
    noisy = Path(__file__).parent / "data" / "pdp_checkpoints_v2" / "adapted"
    with caplog.at_level("WARNING", logger="lerobot_pdp.adapted"):
        assert cli(["search", str(noisy), "--env", "reach-around", "--scene", "3", "--budget", "1",
                    "--rollouts-per-candidate", "1", "--init", "adaptation", "--no-progress"]) == 0
    assert "carries 13 fitted chunk noises besides its latent; the search moves the latent alone" in caplog.text


def test_cli_search_with_finish_scores_the_tasks_success_after_the_way_points(checkpoint, tmp_path, capsys):
    out, hist = tmp_path / "searched", tmp_path / "history.json"
    assert cli(["search", str(checkpoint), "--env", "reach-around", "--scene", "3", "--waypoints", "scene", "--finish",
                "--budget", "2", "--rollouts-per-candidate", "1", "--confirm-rollouts", "0", "--no-progress",
                "--out", str(out), "--history", str(hist)]) == 0
    capsys.readouterr()
    record = json.loads(hist.read_text())
    assert record["objective"]["finish"] is True and len(record["history"]) == 2
    for c in record["history"]:  # a score above 1 only with every way-point passed and the task done
        assert 0 <= c["score"] <= 2 and (c["score"] <= 1 or c["success"] > 0)
    assert json.loads((out / ADAPTATION_INFO).read_text())["objective"]["finish"] is True
    assert "then succeeding" in (out / "README.md").read_text()
    assert cli(["search", str(checkpoint), "--env", "reach-around", "--finish", "--no-progress"]) == 2
    assert "--finish adds the task's success to the way-point score: give --waypoints too" in capsys.readouterr().err


def test_cli_search_says_when_no_candidate_scored_apart(checkpoint, tmp_path, caplog):
    """A search whose candidates all scored the same had nothing to follow: its "best" is the first latent tried,
    and the search says so (with what gives it a signal) instead of presenting it as found, from the command line
    as from Python (search_latent warns)."""
    hist = tmp_path / "history.json"
    with caplog.at_level("WARNING", logger="lerobot_pdp.latent_search"):
        assert cli(["search", str(checkpoint), "--env", "reach-around", "--scene", "3", "--budget", "3",
                    "--rollouts-per-candidate", "1", "--confirm-rollouts", "0", "--no-progress", "--history",
                    str(hist)]) == 0
    scores = {c["score"] for c in json.loads(hist.read_text())["history"]}
    said = "the best latent is just the first one tried; score by way-points (WaypointScore, or --waypoints)"
    assert (said in caplog.text) == (len(scores) == 1), (scores, caplog.text)


def test_cli_search_names_bad_input(checkpoint, tmp_path, capsys):
    base = ["search", str(checkpoint), "--env", "reach-around", "--no-progress"]
    outside, flat = tmp_path / "outside.json", tmp_path / "flat.json"
    outside.write_text(json.dumps([[0.0, -0.3, 0.4], [0.0, 0.0, 1.5]]))
    flat.write_text(json.dumps([[0.0, 0.3]]))
    cases = [
        (["--waypoints", str(outside)], rf"{outside}: way-point 1 \[0.0, 0.0, 1.5\] lies outside reach-around's workspace"),
        (["--waypoints", str(flat)], rf"{flat}: reach-around way-points are points of 3 coordinates"),
        (["--waypoints", str(tmp_path / "none.json")], "way-point file .*none.json does not exist"),
        (["--waypoints", "scene"], r"waypoints='scene' but the scene has no 'waypoints' \(the shipped reach-around "
                                   r"scenes with way-points: 3, val3, val4; or give them in a JSON/YAML file\)"),
        (["--waypoints", "scene", "--scene", "3", "--radius", "0"], "--radius must be a finite number > 0"),
        (["--budget", "0"], "--budget must be >= 1, got 0"),
        (["--history", str(tmp_path / "nodir" / "h.json")], r"--history .*h.json: folder .*nodir does not exist"),
        (["--budget", "1"], "--budget 1 rollouts pays for no candidate of --rollouts-per-candidate 2"),
        (["--scene", "val9"], "ships no validation scene 'val9'"),
        (["--init", "adaptation", "--budget", "1", "--rollouts-per-candidate", "1"], "carries no adaptation.safetensors"),
        (["--score", "reward", "--waypoints", "scene", "--scene", "3"], "--score reward and --waypoints are two objectives"),
        (["--out", str(outside / "sub")], r"--out .*sub: .*outside.json is a file, not a folder"),
        (["--out", str(tmp_path / "o"), "--history", str(tmp_path / "o")], "--out and --history are both"),
        (["--waypoints", str(tmp_path)], "is a folder: give a JSON/YAML file"),
        (["--waypoints", "[[0, 0, 0.5]]"], "points are not read from the command line"),
    ]
    for extra, match in cases:
        assert cli([*base, *extra]) == 2, extra
        assert __import__("re").search(match, capsys.readouterr().err), (extra, match)
    assert cli(["search", str(tmp_path / "nope"), "--env", "reach-around"]) == 2
    assert "no such checkpoint folder" in capsys.readouterr().err
    assert cli(["search", str(checkpoint), "--env", "avoiding", "--budget", "1", "--rollouts-per-candidate", "1",
                "--no-progress"]) == 2
    err = capsys.readouterr().err  # said before the policy loads: no budget warning first
    assert f"--env avoiding does not match checkpoint {checkpoint}: the env's 'observation.state' has shape (4,)" in err
    assert "budget" not in err
