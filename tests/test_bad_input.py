"""Every bad input gets an error (or, where acting on it is legitimate, one warning) that names the file, key,
field or value and what was expected (issue 54). One test per case; no test trains."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors
from policies import small_policy

from lerobot_pdp import PDPConfig, PDPPolicy
from lerobot_pdp.cli import main as lerobot_pdp
from lerobot_pdp.steering import SteerFile, write_steering


@pytest.fixture(scope="module")
def policy(synthetic_meta):
    return small_policy(synthetic_meta)


@pytest.fixture(scope="module")
def checkpoint(policy, synthetic_meta, tmp_path_factory) -> Path:
    """A checkpoint as lerobot-train writes one: weights, config, processors."""
    path = tmp_path_factory.mktemp("bad_input") / "ckpt"
    policy.save_pretrained(path)
    pre, post = make_pre_post_processors(policy.config, dataset_stats=synthetic_meta.stats)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


def _copy(checkpoint: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(checkpoint, tmp_path / "ckpt"))


def _warnings(caplog, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and text in r.getMessage()]


# ---- the steering API


def test_a_recording_with_damaged_metadata_is_named(policy, synthetic_meta, tmp_path):
    rec = Path(shutil.copytree(synthetic_meta.root, tmp_path / "rec"))
    (rec / "meta" / "info.json").write_text("{")
    with pytest.raises(ValueError, match=rf"{rec / 'meta' / 'info.json'} is not valid JSON"):
        policy.fit_latent((rec, 0), steps=1, activate=False)


def test_select_action_names_a_missing_key_or_a_frame_of_another_size(policy):
    policy.reset()
    ok = {"observation.state": torch.zeros(1, 2), "observation.environment_state": torch.zeros(1, 2)}
    with pytest.raises(KeyError, match=r"conditions on 'observation.environment_state' \[B, 2\], which the "
                                       r"observation lacks; it has \['observation.state'\]"):
        policy.select_action({"observation.state": ok["observation.state"]})
    with pytest.raises(ValueError, match=r"'observation.state' has shape \[1, 4\]; this policy expects \[B, 2\]"):
        policy.select_action({**ok, "observation.state": torch.zeros(1, 4)})
    with pytest.raises(ValueError, match=r"expects \[B, 2, 2\] \(its training dataset's feature, a history of "
                                         r"n_obs_steps = 2 frames\)"):  # a history passed whole
        policy.predict_action_chunk({**ok, "observation.state": torch.zeros(1, 2, 3)})
    history = {k: torch.zeros(1, 3, 2) for k in ok}  # one frame too many
    with pytest.raises(ValueError, match=r"has shape \[1, 3, 2\]; this policy expects \[B, 2, 2\]"):
        policy.predict_action_chunk(history)
    for act in (policy.select_action, policy.predict_action_chunk):  # numpy, as an env gives it: not a tensor
        with pytest.raises(TypeError, match=r"observation 'observation.state' is a numpy.ndarray; PDP takes torch "
                                            r"tensors \[B, 2\], as LeRobot's preprocessor gives them"):
            act({k: v.numpy() for k, v in ok.items()})
    policy.reset()
    policy.select_action(ok)  # actions for one env queued; four envs without reset() would get them
    with pytest.raises(ValueError, match=r"a batch of 4 observation\(s\) while actions for a batch of 1 are still "
                                         r"queued: call policy.reset\(\)"):
        policy.select_action({k: v.expand(4, -1) for k, v in ok.items()})
    policy.reset()
    assert policy.select_action({k: v.expand(4, -1) for k, v in ok.items()}).shape == (4, 2)
    policy.reset()
    glitch = {**ok, "observation.environment_state": torch.tensor([[0.1, float("nan")]])}
    with pytest.raises(FloatingPointError, match=r"observation 'observation.environment_state' holds non-finite "
                                                 r"values \(NaN or inf\) after the preprocessor: no action"):
        policy.select_action(glitch)  # named before a chunk is sampled
    policy.reset()


def test_a_latent_far_outside_the_training_latents_warns_once(policy, caplog):
    assert policy.latent_outlier(policy.mode_latents()[0][None]) is None  # the check, without acting
    far, spread = policy.latent_outlier(torch.tensor([[1e6, -1e6]]))
    assert far > 3 and spread > 0
    assert policy.latent_outlier(policy.mode_latents()[0]) is None  # one latent [d_z], as set_latent takes it
    for z in (torch.tensor([1e6, -1e6]), np.array([1e6, -1e6]), [1e6, -1e6]):
        assert policy.latent_outlier(z)[0] > 3
    with pytest.raises(ValueError, match=r"latent has shape \[3\]; expected \[2\] or \[M, 2\]"):
        policy.latent_outlier([1.0, 2.0, 3.0])
    with caplog.at_level(logging.WARNING):
        policy.set_latent(policy.mode_latents()[0])
        assert not _warnings(caplog, "spreads")
        policy.set_latent([1e6, -1e6])
        for _ in range(3):
            policy.current_latent(2)  # acting under it does not warn again
    (msg,) = _warnings(caplog, "spreads")
    assert "[[1000000.0, -1000000.0]]" in msg and "spreads of the training latents from the nearest one" in msg
    assert "warning above 3" in msg
    assert policy.active_latent.tolist() == [[1e6, -1e6]]  # acted on, as asked
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # so far that float32 distances overflow: still far, still said
        policy.set_latent([1e38, -1e38])
    (msg,) = _warnings(caplog, "spreads")
    assert "inf spreads" in msg
    policy.set_latent(None)


def test_a_latent_the_denoiser_overflows_under_is_refused_before_it_acts(synthetic_meta, tmp_path, caplog):
    """A finite latent so large that the denoiser's activations pass float32 (its FiLM scales) would make every action
    non-finite: set_latent refuses it and the latent before it stays; so does a live steering request (logged, the
    robot keeps acting), where it once stopped the robot loop at the next chunk."""
    from lerobot_pdp.steering import SteerFile

    p = small_policy(synthetic_meta)
    for block in p.model.denoiser.blocks():  # as trained: FiLM's last layer is zero only at initialisation
        torch.nn.init.normal_(block.latent_film.mlp[-1].weight, std=0.5)
    good = p.mode_latents()[0]
    p.set_latent(good)
    p.set_latent([1e15, 1e15])  # far, but the network stays finite: acted on (with the far-latent warning)
    for huge in ([1e30, 1e30], torch.tensor([[1e30, -1e30]])):
        p.set_latent(good)
        with pytest.raises(ValueError, match=r"latent \[\[1e\+30, -?1e\+30\]\] makes the denoiser overflow \(non-finite "
                                             r"output\): every action under "
                                             r"it would be non-finite"):
            p.set_latent(huge)
        torch.testing.assert_close(p.active_latent[0], good)
    steer = tmp_path / "steer.json"
    live = SteerFile(steer)
    assert not live.poll(p)  # the policy acts (no request yet); the next one is a live request
    steer.write_text('{"latent": [1e30, 1e30]}')
    with caplog.at_level(logging.ERROR):
        assert not live.poll(p)
    assert "makes the denoiser overflow" in caplog.text and "keeping the current latent" in caplog.text
    torch.testing.assert_close(p.active_latent[0], good)


def test_processors_without_statistics_say_they_do_not_normalise(policy, caplog):
    from lerobot_pdp.processor_pdp import make_pdp_pre_post_processors

    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.processor_pdp"):
        make_pdp_pre_post_processors(policy.config, policy.stats.as_dict())
        assert not caplog.records
        make_pdp_pre_post_processors(policy.config)
    assert "PDP processors built without dataset_stats do not normalise" in caplog.text


def test_a_string_latent_names_the_accepted_types(policy):
    with pytest.raises(TypeError, match=r"latent must be a tensor, a numpy array or a sequence of floats, shape "
                                        r"\[d_z\] or \[M, d_z\].*got str '0.4 -1.2'"):
        policy.set_latent("0.4 -1.2")
    with pytest.raises(TypeError, match=r"latent must be .*got list \['a', 'b'\]"):
        policy.set_latent(["a", "b"])
    for mode in (3, "left-wide"):  # a mode, meant as its latent: where its latent is
        with pytest.raises(TypeError, match=re.escape(f"(a mode's latent: policy.mode_latents()[{mode!r}])")):
            policy.set_latent(mode)
    with pytest.raises(TypeError, match=re.escape("got str '0.4 -1.2' (as numbers: [0.4, -1.2])")):
        policy.set_latent("0.4 -1.2")
    with pytest.raises(ValueError, match=r"latent must have shape \[2\] or \[M, 2\], got \(3,\)"):  # as given
        policy.set_latent(torch.zeros(3))


def test_an_unknown_mode_lists_the_modes(policy):
    means = policy.mode_latents()
    with pytest.raises(KeyError, match=r"no mode 99: the training modes are 0 \(left-tight\), 1 \(left-wide\), "
                                       r"2 \(right-tight\), 3 \(right-wide\)"):
        means[99]
    assert 99 not in means and means.get(99) is None  # still a dict: membership and get() do not raise
    # a cluster id read from a tensor, an id as typed and a mode's name (as `lerobot-pdp steer --mode` takes them)
    # find their mode
    assert torch.equal(means[torch.tensor(1)], means[1]) and torch.equal(means["left-wide"], means[1])
    assert torch.equal(means[" 1 "], means[1])
    with pytest.raises(KeyError, match="no mode '99'"):
        means["99"]


@pytest.mark.parametrize("typed, key", [("3", 3), (" -1 ", -1), ("left-wide", "left-wide"), ("3a", "3a"), (2, 2),
                                        ("", "")])
def test_a_mode_typed_as_digits_is_its_id_everywhere(typed, key):
    """One rule for a mode given as text (steer file, CLI flags, --policy.steer_mode, fit_latent's init)."""
    from lerobot_pdp.cli import _parse_modes
    from lerobot_pdp.steer_requests import mode_key

    assert mode_key(typed) == key and type(mode_key(typed)) is type(key)
    if isinstance(typed, str) and typed.strip():
        assert _parse_modes([typed]) == [key]


def test_fit_latent_bad_steps_init_and_episode_index(policy, synthetic_dataset):
    with pytest.raises(ValueError, match=r"steps must be an integer >= 0 .*got -5"):
        policy.fit_latent((synthetic_dataset, 0), steps=-5)
    with pytest.raises(ValueError, match=r"lr must be a finite number > 0 .*got -1.0"):
        policy.fit_latent((synthetic_dataset, 0), steps=1, lr=-1.0)
    with pytest.raises(ValueError, match=r"init has shape \(3,\) \(3 values\); expected shape \[2\] or \[1, 2\]"):
        policy.fit_latent((synthetic_dataset, 0), steps=0, init=torch.zeros(3))
    with pytest.raises(TypeError, match=rf"episode index must be an integer \(an episode of {synthetic_dataset}\), "
                                        r"got float 0.9"):
        policy.fit_latent((synthetic_dataset, 0.9), steps=0)
    assert policy.fit_latent((synthetic_dataset, np.int64(1)), steps=0, activate=False).steps == 0
    # init as set_latent takes latents (a list, an array); a mode is named as such
    res = policy.fit_latent((synthetic_dataset, 0), steps=0, init=np.array([0.1, 0.2]), activate=False)
    assert torch.allclose(res.z.reshape(-1), torch.tensor([0.1, 0.2]))
    assert policy.fit_latent((synthetic_dataset, 0), steps=0, init=[0.1, 0.2], activate=False).steps == 0
    with pytest.raises(TypeError, match=re.escape("(a mode's latent: policy.mode_latents()[3])")):
        policy.fit_latent((synthetic_dataset, 0), steps=0, init="3")
    with pytest.raises(ValueError, match=re.escape("a mode's latent: init=policy.mode_latents()['left-wide']")):
        policy.fit_latent((synthetic_dataset, 0), steps=0, init="left-wide")
    with pytest.raises(ValueError, match=r"init must be one of 'encoder', 'random', 'zero' or a latent .*got 'encodr'$"):
        policy.fit_latent((synthetic_dataset, 0), steps=0, init="encodr")  # a typo: no mode hint
    for episode in (synthetic_dataset, [str(synthetic_dataset), 0]):  # a folder alone, a list: the tuple it takes
        with pytest.raises(TypeError, match=re.escape(f"one episode of a recording is the tuple "
                                                      f"({str(synthetic_dataset)!r}, <episode index>)")):
            policy.fit_latent(episode, steps=0)


def _recording_with(synthetic_meta, tmp_path: Path, **edit) -> Path:
    """A copy of the training dataset whose info.json is edited: ``fps``, ``robot_type``, or a feature's ``names``."""
    rec = Path(shutil.copytree(synthetic_meta.root, tmp_path / "rec"))
    info = json.loads((rec / "meta" / "info.json").read_text())
    info.update({k: edit[k] for k in ("fps", "robot_type") if k in edit})
    for key, names in edit.get("names", {}).items():
        info["features"][key]["names"] = names
    (rec / "meta" / "info.json").write_text(json.dumps(info))
    return rec


def test_a_checkpoint_keeps_its_training_datas_frame_rate_and_value_names(checkpoint):
    cfg = json.loads((checkpoint / "config.json").read_text())
    assert cfg["dataset_fps"] == 10.0
    assert cfg["dataset_feature_names"] == {"observation.state": ["x", "y"], "observation.environment_state":
                                            ["goal_x", "goal_y"], "action": ["dx", "dy"]}
    assert PDPPolicy.from_pretrained(checkpoint).config.dataset_feature_names == cfg["dataset_feature_names"]


def test_a_recording_naming_its_values_in_another_order_is_refused(policy, synthetic_meta, tmp_path):
    rec = _recording_with(synthetic_meta, tmp_path, names={"action": ["dy", "dx"]})
    with pytest.raises(ValueError, match=re.escape(f"recording {rec} does not match the checkpoint: 'action' names its "
                                                   "values ['dy', 'dx'], in another order than the policy's training "
                                                   "data (['dx', 'dy'])")):
        policy.fit_latent((rec, 0), steps=1, activate=False)
    # a robot's recording names them with LeRobot's hardware suffix: the same values, fitted
    rec = _recording_with(synthetic_meta, tmp_path / "suffix", names={"action": ["dx.vel", "dy.vel"],
                                                                      "observation.state": ["x.pos", "y.pos"]})
    assert policy.fit_latent((rec, 0), steps=0, activate=False).steps == 0
    # other names altogether are another naming, not another order: fitted by position
    rec = _recording_with(synthetic_meta, tmp_path / "other", names={"action": ["a0", "a1"]})
    assert policy.fit_latent((rec, 0), steps=0, activate=False).steps == 0


def test_a_recording_at_another_frame_rate_is_refused(policy, synthetic_meta, tmp_path, checkpoint, capsys):
    rec = _recording_with(synthetic_meta, tmp_path, fps=30)
    with pytest.raises(ValueError, match=re.escape("it was recorded at 30 fps, the policy's training data at 10 fps "
                                                   "(each action spans another time: record at 10 fps, "
                                                   "--dataset.fps=10)")):
        policy.fit_latent((rec, 0), steps=1, activate=False)
    # a recording of the project's simulation steps its env once per frame, whatever fps it is labelled with
    sim = _recording_with(synthetic_meta, tmp_path / "sim", fps=30, robot_type="pdp_sim")
    assert policy.fit_latent((sim, 0), steps=0, activate=False).steps == 0
    f = tmp_path / "steer.json"  # lerobot-pdp steer checks it against the checkpoint before writing the request
    assert lerobot_pdp(["steer", str(f), "--dataset", str(rec), "--policy-path", str(checkpoint)]) == 2
    assert "it was recorded at 30 fps, the policy's training data at 10 fps" in capsys.readouterr().err
    assert not f.exists()


def test_a_demonstration_past_the_actions_the_sampler_makes_warns(policy, synthetic_dataset, caplog):
    """The sampler clips each chunk to the training actions' range: a demonstration that commands faster actions
    cannot be followed by any latent or chunk noise; the fit says so, naming the dim and both ranges."""
    from lerobot_pdp.episodes import read_episodes

    ep = read_episodes(synthetic_dataset, ["observation.state", "observation.environment_state", "action"], [0])[0]
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.adaptation"):
        policy.fit_latent((synthetic_dataset, 0), steps=0, activate=False)
    assert not _warnings(caplog, "cannot produce")
    fast = {k: ep[k] for k in ("observation.state", "observation.environment_state")}
    fast["action"] = ep["action"] * np.array([1.0, 3.0])  # dim 1 three times as fast
    with caplog.at_level(logging.WARNING, logger="lerobot_pdp.adaptation"):
        policy.fit_latent(fast, steps=0, activate=False)
    (msg,) = _warnings(caplog, "cannot produce")
    assert re.search(r"fit_latent: the demonstration commands actions this policy cannot produce: its sampler clips "
                     r"every chunk to the training actions' range \(clip_sample_range=1 in normalised units\); dim 1 "
                     r"\(dy\): \d+ of \d+ frames past it", msg) and "dim 0" not in msg


# ---- live steering: the file and lerobot-pdp steer


def test_steer_cli_refuses_bad_requests_before_writing(checkpoint, synthetic_meta, tmp_path, capsys):
    f = tmp_path / "steer.json"
    assert lerobot_pdp(["steer", str(f), "--latent", "nan", "inf"]) == 2
    assert "latent [nan, inf] has non-finite values [nan, inf]; every value must be a finite number" in capsys.readouterr().err
    assert not f.exists()
    assert lerobot_pdp(["steer", str(f), "--mode", "-1"]) == 2
    assert "mode must be a mode id >= 0 or a mode name, got -1" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--mode", "99", "--policy-path", str(checkpoint)]) == 2
    assert (f"no mode 99 in checkpoint {checkpoint}; its modes are 0 (left-tight), 1 (left-wide), 2 (right-tight), "
            "3 (right-wide)") in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--latent", "1", "2", "3", "--policy-path", str(checkpoint)]) == 2
    assert f"has 3 values; expected 2 (latent_dim of checkpoint {checkpoint})" in capsys.readouterr().err
    assert not f.exists()

    assert lerobot_pdp(["steer", str(f), "--latent", "1", "2"]) == 0
    assert json.loads(f.read_text()) == {"latent": [1.0, 2.0]}
    assert lerobot_pdp(["steer", str(f), "--latent", "1", "2", "3"]) == 2  # no checkpoint: the file's latent size
    assert f"has 3 values; expected 2 (the size of the latent already in {f}" in capsys.readouterr().err
    capsys.readouterr()
    assert lerobot_pdp(["steer", str(f), "--mode", "left-wide", "--policy-path", str(checkpoint)]) == 0
    assert json.loads(f.read_text()) == {"mode": "left-wide"}
    assert f'wrote {f}: {{"mode": "left-wide"}}' in capsys.readouterr().out  # what the file holds, as JSON
    with pytest.raises(ValueError, match="non-finite"):
        write_steering(f, {"latent": [float("nan"), 0.0]})
    assert json.loads(f.read_text()) == {"mode": "left-wide"}  # strict JSON, never NaN
    assert lerobot_pdp(["steer", str(f), "--latent", "0.4", "-1.5e-05"]) == 0  # as Python prints small values
    assert json.loads(f.read_text()) == {"latent": [0.4, -1.5e-05]}
    assert lerobot_pdp(["steer", str(f), "--latent", "-inf", "1"]) == 2
    assert "non-finite values [-inf]" in capsys.readouterr().err
    # a recording to fit: its folder and episode, as the running policy will look for them
    assert lerobot_pdp(["steer", str(f), "--dataset", str(tmp_path / "nowhere")]) == 2
    assert f"recording {tmp_path / 'nowhere'} does not exist" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--dataset", str(tmp_path)]) == 2
    assert f"{tmp_path} is not a LeRobotDataset (no meta/info.json)" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--dataset", str(synthetic_meta.root), "--episode", "999"]) == 2
    assert "no episode 999" in capsys.readouterr().err
    empty = tmp_path / "empty"  # a recording whose only episode was cut off by Ctrl-C (dropped, not saved)
    (empty / "meta").mkdir(parents=True)
    (empty / "meta" / "info.json").write_text(json.dumps({"total_episodes": 0}))
    assert lerobot_pdp(["steer", str(f), "--dataset", str(empty)]) == 2
    assert f"recording {empty} is empty (no saved episode)" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--mode", "1", "--episode", "4"]) == 2
    assert "--episode and --steps go with --dataset" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--episode", "0"]) == 2  # alone: the request it belongs to is named
    assert f"go with --dataset (a recording to fit z to): lerobot-pdp steer {f} --dataset DIR" \
        in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f)]) == 2
    assert "one request is needed: --mode ID|NAME, --latent Z..., --dataset DIR" in capsys.readouterr().err
    assert json.loads(f.read_text()) == {"latent": [0.4, -1.5e-05]}  # none of them written
    # with --policy-path, a recording the policy's fit would refuse: other features, an episode shorter than a chunk
    other = Path(shutil.copytree(synthetic_meta.root, tmp_path / "other"))
    info = json.loads((other / "meta" / "info.json").read_text())
    info["features"]["observation.state"]["shape"] = [3]
    (other / "meta" / "info.json").write_text(json.dumps(info))
    assert lerobot_pdp(["steer", str(f), "--dataset", str(other), "--policy-path", str(checkpoint)]) == 2
    assert "does not match the checkpoint: 'observation.state' has shape (3,)" in capsys.readouterr().err
    import pyarrow.parquet as pq

    short = Path(shutil.copytree(synthetic_meta.root, tmp_path / "short"))
    (episodes,) = (short / "meta" / "episodes").glob("**/*.parquet")
    table = pq.read_table(episodes)
    lengths = table.column("length").to_pylist()
    pq.write_table(table.set_column(table.schema.get_field_index("length"), "length",
                                    __import__("pyarrow").array([5] + lengths[1:], table.schema.field("length").type)),
                   episodes)
    assert lerobot_pdp(["steer", str(f), "--dataset", str(short), "--policy-path", str(checkpoint)]) == 2
    assert "episode 0 has 5 frames, shorter than one action chunk (horizon 16)" in capsys.readouterr().err
    assert lerobot_pdp(["steer", str(f), "--dataset", str(short), "--episode", "1", "--policy-path", str(checkpoint)]) == 0
    assert json.loads(f.read_text())["episode"] == 1
    # a checkpoint without mode labels: its modes are discovered at load, so a mode cannot be checked here; said so
    from safetensors.torch import load_file, save_file

    unlabelled = _copy(checkpoint, tmp_path)
    weights = load_file(str(unlabelled / "model.safetensors"))
    weights["behavior_mode"] = torch.full_like(weights["behavior_mode"], -1)
    save_file(weights, str(unlabelled / "model.safetensors"))
    assert lerobot_pdp(["steer", str(f), "--mode", "3", "--policy-path", str(unlabelled)]) == 0
    assert f"(mode not checked: {unlabelled} has no mode labels; its modes are the clusters" in capsys.readouterr().out


def test_steer_into_a_missing_folder_names_the_folder(tmp_path, capsys):
    assert lerobot_pdp(["steer", str(tmp_path / "nowhere" / "steer.json"), "--mode", "1"]) == 2
    err = capsys.readouterr().err
    assert f"cannot write the steering file {tmp_path / 'nowhere' / 'steer.json'}: folder {tmp_path / 'nowhere'} " \
           "does not exist" in err and ".tmp" not in err
    assert lerobot_pdp(["steer", str(tmp_path), "--mode", "1"]) == 2  # a folder where the file goes
    err = capsys.readouterr().err
    assert f"{tmp_path} is a folder: give the steering file's path" in err and ".tmp" not in err


@pytest.mark.parametrize(("flag", "value", "said"), [
    ("--seed", "-5", "must be an integer >= 0, got '-5'"),
    ("--episode", "0.9", "must be an integer >= 0, got '0.9'"),
    ("--steps", "-1", None),
    ("--lr", "nan", "must be a finite number > 0, got 'nan'"),
])
def test_a_bad_number_is_named_by_its_flag(capsys, flag, value, said):
    """Refused by the parser, naming the flag (the functions behind it would name a Python parameter, numpy a seed,
    or read 0.9 as episode 0), before any file is read."""
    commands = {"make-dataset": ["--env", "reach-around", "--out", "x"], "adapt": ["ckpt", "--demo", "d", "--out", "x"],
                "teach": ["ckpt", "--demo", "d", "--data", "d", "--out", "x"], "search": ["ckpt", "--env", "reach-around"]}
    takes = {"--seed": list(commands), "--episode": ["adapt", "teach"], "--steps": ["adapt", "teach"],
             "--lr": ["adapt", "teach"]}
    for command in takes[flag]:
        with pytest.raises(SystemExit) as ended:
            lerobot_pdp([command, *commands[command], flag, value])
        assert ended.value.code == 2
        expected = said or f"must be an integer >= {1 if command == 'teach' else 0}, got '-1'"
        assert f"argument {flag}: {expected}" in capsys.readouterr().err, command
    for args, said in ((["make-dataset", *commands["make-dataset"], "--episodes-per-mode", "0"],
                        "argument --episodes-per-mode: must be an integer >= 1, got '0'"),
                       (["teach", *commands["teach"], "--demo-share", "1.5"],
                        "argument --demo-share: must be a finite number > 0 and <= 1, got '1.5'")):
        with pytest.raises(SystemExit):
            lerobot_pdp(args)
        assert said in capsys.readouterr().err


def test_a_steer_file_rewritten_in_place_within_one_tick_is_seen(policy, tmp_path):
    f = tmp_path / "steer.json"
    f.write_text('{"latent": [0.1, 0.2]}')
    steer = SteerFile(f)
    assert steer.poll(policy) and policy.active_latent.tolist() == [[pytest.approx(0.1), pytest.approx(0.2)]]
    st = os.stat(f)
    with open(f, "r+") as h:  # same inode, same size, then the old mtime: a rewrite within one clock tick
        h.write('{"latent": [0.3, 0.4]}')
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    now = os.stat(f)
    assert (now.st_mtime_ns, now.st_size, now.st_ino) == (st.st_mtime_ns, st.st_size, st.st_ino)
    assert steer.poll(policy) and policy.active_latent.tolist() == [[pytest.approx(0.3), pytest.approx(0.4)]]
    assert not steer.poll(policy)  # unchanged: not applied again
    f.write_text('{"latent": [NaN, 0.0]}')
    assert not steer.poll(policy) and policy.active_latent.tolist()[0][0] == pytest.approx(0.3)
    policy.set_latent(None)


# ---- checkpoints on disk


def test_a_damaged_weights_file_is_named(checkpoint, tmp_path):
    ckpt = _copy(checkpoint, tmp_path)
    weights = ckpt / "model.safetensors"
    data = weights.read_bytes()
    for cut in (100, len(data) // 2):  # "invalid header length", then "incomplete metadata"
        weights.write_bytes(data[:cut])
        with pytest.raises(ValueError, match=rf"{weights} is not a readable safetensors file .*damaged"):
            PDPPolicy.from_pretrained(ckpt)


def test_non_finite_processor_statistics_are_refused_at_load_by_file_and_key(checkpoint, tmp_path):
    """The postprocessor's statistics unnormalise every action after PDP's own check of the chunk: a NaN there
    would reach the robot, so the checkpoint is refused as it loads (the preprocessor's likewise)."""
    from safetensors.torch import load_file, save_file

    for kind in ("postprocessor", "preprocessor"):
        ckpt = _copy(checkpoint, tmp_path / kind)
        (stats_file,) = ckpt.glob(f"policy_{kind}_step_*.safetensors")
        stats = load_file(stats_file)
        key = next(k for k in sorted(stats) if k.endswith(".max"))
        stats[key][0] = float("nan") if kind == "postprocessor" else float("inf")
        save_file(stats, stats_file)
        with pytest.raises(ValueError, match=rf"{stats_file}: statistic '{re.escape(key)}' holds 1 non-finite value"):
            PDPPolicy.from_pretrained(ckpt)


def test_latent_map_on_a_damaged_checkpoint_names_the_file(checkpoint, tmp_path, capsys):
    ckpt = _copy(checkpoint, tmp_path)
    (ckpt / "model.safetensors").write_bytes((ckpt / "model.safetensors").read_bytes()[:100])
    assert lerobot_pdp(["latent-map", str(ckpt), "--out", str(tmp_path / "map.png")]) == 2
    assert f"{ckpt / 'model.safetensors'} is not a readable safetensors file" in capsys.readouterr().err
    assert lerobot_pdp(["latent-map", str(checkpoint), "--out", str(tmp_path)]) == 2  # a folder: named before loading
    assert f"--out {tmp_path} is a folder: give the PNG file to write" in capsys.readouterr().err


def test_a_damaged_config_json_is_named(checkpoint, tmp_path):
    ckpt = _copy(checkpoint, tmp_path)
    (ckpt / "config.json").write_text((ckpt / "config.json").read_text()[:1500])
    for load in (PDPPolicy.from_pretrained, PDPConfig.from_pretrained):
        with pytest.raises(ValueError, match=rf"{ckpt / 'config.json'} is not valid JSON \(.*line \d+ column \d+"):
            load(ckpt)


def test_an_edited_latent_dim_names_the_field(checkpoint, tmp_path):
    ckpt = _copy(checkpoint, tmp_path)
    cfg = json.loads((ckpt / "config.json").read_text())
    (ckpt / "config.json").write_text(json.dumps({**cfg, "latent_dim": 3}))
    with pytest.raises(ValueError, match=rf"does not match its config: latent_dim is 2 in the weights, 3 in "
                                         rf"{ckpt / 'config.json'}"):
        PDPPolicy.from_pretrained(ckpt)


def test_a_network_size_given_on_the_command_line_names_the_flag(checkpoint, monkeypatch):
    """``--policy.path=CKPT --policy.latent_dim=4``: the flag is named, not an edit of config.json."""
    monkeypatch.setattr("sys.argv", ["lerobot-eval", f"--policy.path={checkpoint}", "--policy.latent_dim=4"])
    cfg = PDPConfig.from_pretrained(checkpoint)
    cfg.latent_dim = 4
    with pytest.raises(ValueError, match=re.escape(f"--policy.latent_dim=4 (saved: 2) given on the command line change "
                                                   f"the networks' shapes, but the weights of {checkpoint}")):
        PDPPolicy.from_pretrained(checkpoint, config=cfg)


def test_a_checkpoint_built_for_another_env_names_the_features(checkpoint):
    """lerobot-eval builds the policy's features from --env.type: an env the policy was not trained on is named as
    such (the features that differ), not as an edited config.json."""
    from lerobot.configs import FeatureType, PolicyFeature

    cfg = PDPConfig.from_pretrained(checkpoint)
    cfg.output_features = {"action": PolicyFeature(FeatureType.ACTION, (3,))}  # what another env would give
    with pytest.raises(ValueError, match=r"was trained on other inputs or outputs than this run gives it: 'action' "
                                         r"is \(3,\), trained on \(2,\)\. Is this the env \(--env.type"):
        PDPPolicy.from_pretrained(checkpoint, config=cfg)


def test_a_missing_checkpoint_folder_is_named(tmp_path):
    for missing in (tmp_path / "nowhere", "outputs/train/nowhere/pretrained_model"):
        with pytest.raises(FileNotFoundError, match=rf"no such checkpoint folder: {missing} \(give"):
            PDPPolicy.from_pretrained(missing)
    # what could be a Hub repo id (LeRobot's commands pass one as a Path), offline and not cached: named, not
    # huggingface_hub's "check your connection"
    for missing in ("runs/nowhere", Path("runs/nowhere")):
        with pytest.raises(FileNotFoundError, match=r"no such checkpoint folder: runs/nowhere \(from .*\), and the "
                                                    r"Hub cannot be asked for a repo of that name \(HF_HUB_OFFLINE"):
            PDPPolicy.from_pretrained(missing)


def test_missing_processor_files_are_named(checkpoint, tmp_path, caplog, monkeypatch):
    ckpt = _copy(checkpoint, tmp_path)
    (ckpt / "policy_preprocessor.json").unlink()
    with caplog.at_level(logging.INFO, logger="lerobot_pdp.checkpoint_files"):
        PDPPolicy.from_pretrained(ckpt)  # in-process: loads, saying what lerobot-eval would miss
    assert f"{ckpt} lacks LeRobot's processor files ['policy_preprocessor.json']" in caplog.text
    monkeypatch.setattr("sys.argv", ["/venv/bin/lerobot-eval", f"--policy.path={ckpt}"])
    with pytest.raises(FileNotFoundError, match=rf"lerobot-eval: {ckpt} lacks LeRobot's processor files "
                                                r"\['policy_preprocessor.json'\].*'requires migration'; it does not"):
        PDPPolicy.from_pretrained(ckpt)


# ---- the config on LeRobot's command line


@pytest.mark.parametrize("arg, message", [("--policy.latent_dim=0", "latent_dim must be >= 1, got 0"),
                                          ("--policy.horizon=0", "horizon must be >= 1, got 0")])
def test_an_invalid_policy_field_on_the_command_line_shows_pdps_message(arg, message):
    """draccus (LeRobot's parser) replaces a ValueError raised while building the config by "Couldn't
    instantiate class PDPConfig"; PDP's own message must reach the user."""
    import draccus
    from draccus.utils import DecodingError
    from lerobot.configs.train import TrainPipelineConfig

    with pytest.raises(DecodingError, match=rf"Invalid PDPConfig: {message}"):
        draccus.parse(TrainPipelineConfig, args=["--dataset.repo_id=local/x", "--policy.type=pdp", arg])
    with pytest.raises(ValueError, match=rf"Invalid PDPConfig: {message}"):  # a Python caller: a ValueError
        PDPConfig(**{arg.split("=")[0].removeprefix("--policy."): 0})


# ---- training data


def test_a_damaged_soft_dtw_cache_is_recomputed_with_a_warning(tmp_path, caplog):
    from lerobot_pdp.behavior import trace_distances

    traces = np.random.default_rng(0).normal(size=(4, 16, 2))
    d = trace_distances(traces, 1e-2, False, cache_dir=tmp_path, progress=False)
    (cache,) = tmp_path.glob("trace_distances_*.npy")
    cache.write_bytes(cache.read_bytes()[:40])
    report: dict = {}
    with caplog.at_level(logging.WARNING):
        again = trace_distances(traces, 1e-2, False, cache_dir=tmp_path, progress=False, report=report)
    (msg,) = _warnings(caplog, "soft-DTW cache")
    assert f"soft-DTW cache {cache} is unreadable" in msg and "recomputing it" in msg
    assert report["source"] == "computed" and np.array_equal(again, d)
    assert np.array_equal(np.load(cache), d)  # rewritten whole


def test_an_sdtw_gamma_that_drowns_the_distances_warns(tmp_path, caplog):
    """A large sdtw_gamma makes soft-DTW dip below 0 between different traces (clamped to 0): the geometry term
    would treat them as one behaviour. Said, computed or read from the cache; the default gamma says nothing."""
    from lerobot_pdp.behavior import trace_distances

    traces = np.random.default_rng(0).normal(scale=0.1, size=(6, 16, 2))
    for _ in range(2):  # computed, then read from the cache
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            trace_distances(traces, 10.0, False, cache_dir=tmp_path, progress=False)
        (msg,) = _warnings(caplog, "sdtw_gamma")
        assert re.search(r"soft-DTW with sdtw_gamma=10 puts \d+ of the 30 distances between different behaviours at 0",
                         msg) and "--policy.sdtw_normalize=true" in msg
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        trace_distances(traces, 1e-5, False, cache_dir=tmp_path, progress=False)
        trace_distances(np.concatenate([traces[:2]] * 3), 1e-5, False, cache_dir=tmp_path, progress=False)  # copies
        trace_distances(traces, 10.0, True, cache_dir=tmp_path, progress=False)  # the divergence: >= 0 by design
    assert not _warnings(caplog, "sdtw_gamma")


def test_a_one_episode_dataset_warns_naming_it(tmp_path, caplog):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from synthetic import write_dataset

    root = write_dataset(tmp_path / "one", episodes_per_mode=1, modes=(0,))
    with caplog.at_level(logging.WARNING):
        small_policy(LeRobotDatasetMetadata("local/synthetic", root=root))
    (msg,) = _warnings(caplog, "trains on one episode")
    assert f"PDP trains on one episode of {root}" in msg and "L_geo" in msg and "is 0" in msg


def test_episodes_shorter_than_a_chunk_are_named(synthetic_meta, caplog):
    """Training takes episodes shorter than one action chunk (their chunks padded) but a fit refuses such a
    demonstration: said when training starts, naming the episodes and their lengths."""
    with caplog.at_level(logging.WARNING):
        small_policy(synthetic_meta, dataset_episodes=[0, 1])
    assert not _warnings(caplog, "shorter than one action chunk")
    with caplog.at_level(logging.WARNING):
        policy = small_policy(synthetic_meta, dataset_episodes=[0, 1], horizon=64, drop_n_last_frames=7)
    (msg,) = _warnings(caplog, "shorter than one action chunk")
    lengths = policy.model.bank.end.tolist()
    assert f"2 episode(s) are shorter than one action chunk (horizon 64 frames): 0 ({lengths[0]} frames), 1 " in msg
    assert "PDP trains on them (each chunk padded" in msg
    caplog.clear()  # no longer than LeRobot's sampler drops at an episode's end: skipped whole, said so
    with caplog.at_level(logging.WARNING):
        small_policy(synthetic_meta, dataset_episodes=[0, 1], horizon=64, drop_n_last_frames=55)
    (msg,) = _warnings(caplog, "shorter than one action chunk")
    assert "LeRobot's sampler skips 2 of them whole (no more frames than drop_n_last_frames=55): the " \
           "denoiser never trains on them" in msg


def test_an_unknown_steer_mode_names_the_checkpoints_modes():
    """``--policy.steer_mode`` of a mode the checkpoint lacks (lerobot-eval, lerobot-rollout): its modes by id and name."""
    from pathlib import Path

    taught = PDPPolicy.from_pretrained(Path(__file__).parent / "data" / "pdp_checkpoints_v2" / "taught")
    taught.config.steer_mode = 12
    with pytest.raises(KeyError, match=r"steer_mode 12 is not a mode of this checkpoint \(an id or a name\); its modes "
                                       r"are 0 \(over-tight\).* 8 \(taught: episode 0 of ra_s3\)"):
        taught.apply_config_steering()
    taught.config.steer_mode = "taught: episode 0 of ra_s3"  # a name, as --policy.steer_mode takes it too
    taught.apply_config_steering()
    torch.testing.assert_close(taught.current_latent()[0], taught.mode_latents()[8])


def test_a_state_of_another_size_is_named_by_the_preprocessor(checkpoint):
    """LeRobot's normaliser failed on it with "The size of tensor a (5) must match the size of tensor b (6)"; the
    checkpoint's preprocessor names the key and the size it expects, and lets the right size through."""
    p = PDPPolicy.from_pretrained(checkpoint)
    pre, _ = make_pre_post_processors(p.config, pretrained_path=str(checkpoint))
    state, env = (p.config.input_features[k].shape[0] for k in ("observation.state", "observation.environment_state"))
    obs = {"observation.state": torch.zeros(state + 1), "observation.environment_state": torch.zeros(env)}
    with pytest.raises(ValueError, match=rf"observation 'observation.state' has shape \[{state + 1}\]; this policy "
                                         rf"expects \[..., {state}\], its training dataset's observation.state"):
        pre(obs)
    obs["observation.state"] = torch.zeros(state)
    assert pre(obs)["observation.state"].shape == (1, state)


def test_an_error_raised_inside_a_library_says_how_to_see_where(monkeypatch, capsys):
    """lerobot-pdp prints its errors as one line; one PDP did not raise itself (inside torch, say) adds how to see
    its traceback, and LEROBOT_PDP_TRACEBACK=1 lets it run out with it."""
    import lerobot_pdp.cli as cli

    monkeypatch.setattr(cli, "cmd_label_modes", lambda args: torch.zeros(2) @ torch.zeros(3))
    assert lerobot_pdp(["label-modes", "x", "--from-tasks"]) == 2
    err = capsys.readouterr().err
    assert "lerobot-pdp label-modes: error: " in err and "(RuntimeError not raised by lerobot-pdp's own checks; " \
        "LEROBOT_PDP_TRACEBACK=1 shows the traceback)" in err
    monkeypatch.undo()
    assert lerobot_pdp(["label-modes", "missing-folder", "--from-tasks"]) == 2  # PDP's own message: one line
    assert "shows the traceback" not in capsys.readouterr().err
    monkeypatch.setenv("LEROBOT_PDP_TRACEBACK", "1")
    with pytest.raises(FileNotFoundError, match="dataset folder missing-folder does not exist"):
        lerobot_pdp(["label-modes", "missing-folder", "--from-tasks"])
