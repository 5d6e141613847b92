"""``lerobot-pdp``: the command line beside LeRobot's: datasets from the suite's experts, the benchmark, and the
tools around a checkpoint (latent map, steering, search, adaptation, teaching, the explorer).

Each subcommand is a ``cmd_<name>(args) -> int`` function registered by an ``add_<name>_parser`` helper and
listed in ``SUBCOMMANDS``; heavy imports (torch, LeRobot) happen inside the ``cmd_`` functions, so that a wrong
argument is named at once.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from lerobot_pdp.checkpoint_files import require_checkpoint_files, require_new_folder
from lerobot_pdp.console import latent_text
from lerobot_pdp.search_defaults import CONFIRM_ROLLOUTS, WAYPOINT_RADIUS
from lerobot_pdp.steer_requests import mode_key

if TYPE_CHECKING:  # the benchmark pulls in torch and LeRobot: imported only when a command needs it
    from lerobot_pdp.benchmark.settings import BenchmarkConfig


# The suite's envs, named in help texts. Listed here because importing lerobot_pdp.envs registers LeRobot's env
# configs (seconds); tests/test_cli_startup.py checks the list against envs.SUITE.
SUITE_ENVS = ("avoiding", "kitchen-microwave", "pick-place", "reach-around")


def _check_new_path(path: Path | None, flag: str) -> None:
    """An output path checked before any work: it must not exist, and :func:`_check_parent`."""
    if path is None:
        return
    if path.exists():
        raise FileExistsError(f"{flag} {path} exists{' (a folder)' if path.is_dir() else ''}: give a new path")
    _check_parent(path, flag)


def _check_parent(path: Path, flag: str) -> None:
    """The folder ``path`` goes into (its nearest existing ancestor) is a folder this process can write into: a
    file on the way, or an unwritable place, is named."""
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise NotADirectoryError(f"{flag} {path}: {parent} is a file, not a folder")
    try:  # a probe, not os.access: root may write anywhere by permissions, yet not into /proc
        os.rmdir(tempfile.mkdtemp(prefix=".pdp-probe-", dir=parent))
    except OSError as e:
        raise PermissionError(f"{flag} {path}: cannot write into {parent} ({e.strerror})") from e


def _env_names() -> list[str]:
    return list(SUITE_ENVS)


def _add_env_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", required=True, help=f"suite env, one of {', '.join(_env_names())} (its gym id, e.g. "
                   "lerobot_pdp/ReachAround-v0, or its --env.type name, pdp_reach_around, names it too)")


def _parse_modes(values: Sequence[str] | None) -> list[int | str] | None:
    if not values:
        return None
    out: list[int | str] = []
    for v in values:
        for part in v.split(","):
            part = part.strip()
            if part:
                out.append(mode_key(part))
    return out


# ---- make-dataset ----------------------------------------------------------------------------------


def add_make_dataset_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "make-dataset",
        help="generate scripted demonstrations as a LeRobotDataset v3",
        description="Run the scripted expert per mode (or along way-points) and write a LeRobotDataset whose "
        "episode task strings carry the mode label: state-only, or with --camera also camera images stored as "
        "video (observation.images.<camera>).",
    )
    _add_env_argument(p)
    p.add_argument("--scene", default="0",
                   help="scene index 0-3, a validation scene (val1, val2, ...) or a scene file (JSON/YAML); default 0")
    p.add_argument("--episodes-per-mode", type=_count, default=10, help="demonstrations per mode (default 10)")
    p.add_argument("--seed", type=_seed, default=0, help="seed of all jitter; same seed -> same dataset (default 0)")
    p.add_argument("--out", required=True, type=Path, help="output dataset directory (must not exist)")
    p.add_argument("--modes", nargs="+", default=None,
                   help="subset of modes, by id or name (space- or comma-separated); default all")
    p.add_argument("--waypoints", default=None,
                   help="record along way-points instead of mode templates: a JSON/YAML file (a list of "
                        "points or a scene file) or 'scene' for the scene's own")
    p.add_argument("--max-attempts", type=_count, default=20, help="tries per episode before giving up (default 20)")
    p.add_argument("--camera", default=None,
                   help="record camera images too: a camera of the env (reach-around: top, front, oblique; "
                        "avoiding: top; pick-place: top, side, oblique), or several comma-separated")
    p.add_argument("--image-size", default="96", help="camera image size, N or HxW pixels (default 96)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=cmd_make_dataset)


def cmd_make_dataset(args: argparse.Namespace) -> int:
    from lerobot_pdp.envs.recording import make_dataset

    if args.camera:  # the AV1 encoder logs its whole configuration per episode; keep only its errors
        os.environ.setdefault("SVT_LOG", "1")

    out = make_dataset(
        args.env,
        args.out,
        scene=args.scene,
        episodes_per_mode=args.episodes_per_mode,
        seed=args.seed,
        modes=_parse_modes(args.modes),
        waypoints=args.waypoints,
        progress=not args.no_progress,
        max_attempts=args.max_attempts,
        camera=args.camera,
        image_size=args.image_size,
    )
    print(f"wrote {out}")
    return 0


# ---- plot-dataset ----------------------------------------------------------------------------------


def add_plot_dataset_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot-dataset",
        help="plot a dataset's demonstrations coloured by mode over the scene",
        description="Top view (plus side and front views for 3-D envs) of every episode, coloured by mode.",
    )
    p.add_argument("dataset", type=Path, help="dataset directory written by make-dataset")
    p.add_argument("--out", required=True, type=Path, help="output PNG")
    p.add_argument("--scene", default=None, help="scene to draw (default: the one the dataset was made in)")
    p.add_argument("--env", default=None, help="env name, for datasets not made by make-dataset")
    p.add_argument("--waypoints", default=None,
                   help="way-points to draw in order: a JSON/YAML file (a list of points or a scene file with "
                   "'waypoints', as search --waypoints takes) or 'scene' for the drawn scene's own (default: the "
                   "ones the dataset was recorded along, if any)")
    p.set_defaults(func=cmd_plot_dataset)


def cmd_plot_dataset(args: argparse.Namespace) -> int:
    from lerobot_pdp.envs import get_suite_env
    from lerobot_pdp.envs.plotting import plot_dataset

    if args.env is not None:
        get_suite_env(args.env)  # an unknown name is said as such, before the dataset is compared with it

    out = plot_dataset(args.dataset, args.out, scene=args.scene, env=args.env, waypoints=args.waypoints)
    print(f"wrote {out}")
    return 0


def add_label_modes_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "label-modes",
        help="add episode-level mode labels to an existing LeRobotDataset (meta/mode_labels.json)",
        description="Writes DATASET/meta/mode_labels.json, which PDP reads as each episode's mode (its task "
        'strings stay as they are). Format: {"episodes": {"<episode index>": <mode id>, ...}, "names": '
        '{"<mode id>": "<name>", ...}}; every episode labelled, ids are integers >= 0, names optional. An existing '
        "file is replaced whole (e.g. one a resumed recording left labelling only its earlier episodes).",
    )
    p.add_argument("dataset", type=Path, help="a local LeRobotDataset folder")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--labels", type=Path, help="a JSON file in the format above")
    src.add_argument("--from-tasks", action="store_true",
                     help='take the labels from task strings of the form "mode <id>: <name>"')
    p.set_defaults(func=cmd_label_modes)


def cmd_label_modes(args: argparse.Namespace) -> int:
    from lerobot_pdp.episodes import (
        parse_task_mode,
        parse_task_name,
        read_episodes,
        read_mode_labels_file,
        write_mode_labels,
    )

    if args.labels is not None:
        labels, names = read_mode_labels_file(args.labels)
    else:
        labels, names = {}, {}
        # the task strings alone: an existing label file (stale after a resumed recording) is replaced
        for ep, item in read_episodes(args.dataset, [], mode_labels=False).items():
            mode = parse_task_mode(item["task"])
            if not isinstance(mode, int):
                raise ValueError(f"{args.dataset}: episode {ep}'s task {item['task']!r} carries no 'mode <id>: <name>' "
                                 "label; give --labels")
            labels[ep] = mode
            names.setdefault(mode, parse_task_name(item["task"]))
    path = write_mode_labels(args.dataset, labels, names)
    print(f"wrote {path}: {len(labels)} episodes, {len(set(labels.values()))} modes")
    return 0


def add_latent_map_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "latent-map",
        help="draw a PDP checkpoint's latent space: its training behaviors by mode or discovered cluster",
        description="Scatter of every training behavior's latent, coloured by its mode label (or by the cluster "
        "policy.discover_modes() finds when the data has no labels), and the behaviors' traces per mode; an adapted "
        "checkpoint's latent is marked with a diamond.",
    )
    p.add_argument("checkpoint", type=Path, help="a pretrained_model folder (config.json + model.safetensors)")
    p.add_argument("--out", required=True, type=Path, help="output PNG")
    p.add_argument("--k", type=int, default=None,
                   help="colour by k discovered clusters even where labels exist (default: labels, else the "
                   "clusters policy.discover_modes() finds in the behavior traces)")
    p.set_defaults(func=cmd_latent_map)


def cmd_latent_map(args: argparse.Namespace) -> int:
    require_checkpoint_files(args.checkpoint)  # named before torch and LeRobot are imported
    if args.k is not None and args.k < 1:
        raise ValueError(f"--k must be >= 1 (clusters to colour by), got {args.k}")
    from lerobot_pdp import PDPPolicy
    from lerobot_pdp.latent_map import draw_latent_map

    if args.out.is_dir():
        raise IsADirectoryError(f"--out {args.out} is a folder: give the PNG file to write (e.g. {args.out / 'map.png'})")
    _check_parent(args.out, "--out")
    policy = PDPPolicy.from_pretrained(args.checkpoint)
    policy.eval()
    print(f"wrote {draw_latent_map(policy, args.out, k=args.k)}")
    return 0


def add_steer_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "steer",
        help="steer a running PDP: write its --policy.steer_file (a mode, a latent or a recording to fit)",
        description="Write one steering request, whole, to the file a running PDP polls at each new action "
        "chunk (--policy.steer_file=FILE, e.g. under lerobot-rollout): the robot changes behavior at its next "
        "chunk, without reloading the policy.",
    )
    p.add_argument("file", type=Path, help="the policy's --policy.steer_file")
    # argparse reads "-1.5e-05" as an option (its negative-number rule knows no exponents): latents printed by
    # Python look like that
    p._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|nan)$", re.IGNORECASE)
    g = p.add_mutually_exclusive_group()  # one is needed: cmd_steer says which go together
    g.add_argument("--mode", help="a training mode, by id or name")
    g.add_argument("--latent", type=float, nargs="+", help="a latent z (latent_dim values)")
    g.add_argument("--dataset", help="a recording (LeRobotDataset folder) to fit z to")
    g.add_argument("--default", action="store_true", help="back to the base policy's default latent "
                   "(--policy.inference_latent; drops an adapted checkpoint's latent)")
    p.add_argument("--episode", type=int, default=None, help="episode of --dataset (default 0)")
    p.add_argument("--steps", type=int, default=None, help="fitting steps for --dataset (default: fit_steps)")
    p.add_argument("--policy-path", type=Path, default=None,
                   help="the running policy's checkpoint folder: the request is checked against its latent_dim and "
                   "modes before it is written (without it: the form, finite values, and the latent size of the "
                   "request already in FILE)")
    p.set_defaults(func=cmd_steer)


def cmd_steer(args: argparse.Namespace) -> int:
    from lerobot_pdp.steer_requests import checkpoint_target, file_target, write_steering

    if args.dataset is not None:
        request: dict = {"dataset": str(Path(args.dataset).resolve()),
                         "episode": 0 if args.episode is None else args.episode}
        if args.steps is not None:
            request["steps"] = args.steps
    elif args.episode is not None or args.steps is not None:
        raise ValueError("--episode and --steps go with --dataset (a recording to fit z to): "
                         f"lerobot-pdp steer {args.file} --dataset DIR --episode N")
    elif args.mode is None and args.latent is None and not args.default:
        raise ValueError("one request is needed: --mode ID|NAME, --latent Z..., --dataset DIR "
                         "(with --episode, --steps) or --default")
    elif args.mode is not None:
        request = {"mode": mode_key(args.mode)}
    else:
        request = {"latent": None if args.default else args.latent}
    target = checkpoint_target(args.policy_path) if args.policy_path is not None else file_target(args.file)
    write_steering(args.file, request, target)
    note = ""
    if "mode" in request and args.policy_path is None:
        note = " (mode not checked against a checkpoint: --policy-path checks it)"
    elif "mode" in request and target.modes is None:
        note = (f" (mode not checked: {args.policy_path} has no mode labels; its modes are the clusters the policy "
                "discovers when it loads, shown by lerobot-pdp latent-map)")
    print(f"wrote {args.file}: {json.dumps(request)}{note}")  # as the file holds it
    return 0


def add_demonstration_arguments(p: argparse.ArgumentParser, written: str, demo_required: bool = True,
                                episode_help: str | None = None) -> None:
    """The checkpoint, the demonstration (dataset folder and episode) and the ``written`` checkpoint's folder;
    ``episode_help``: ``--episode`` takes several indices, so described."""
    p.add_argument("checkpoint", type=Path, help="a PDP pretrained_model folder (config.json + model.safetensors)")
    p.add_argument("--demo", required=demo_required, type=Path, help="the demonstration: a LeRobotDataset folder")
    if episode_help is None:
        p.add_argument("--episode", type=_non_negative, default=0, help="its episode index (default 0)")
    else:
        p.add_argument("--episode", type=_non_negative, nargs="+", default=[0], help=episode_help)
    p.add_argument("--out", required=True, type=Path, help=f"the {written} checkpoint folder to write (must not exist)")


def add_adapt_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "adapt",
        help="adapt a PDP checkpoint to one demonstration and write it as an adapted checkpoint",
        description="Fit z (one per phase for segmented policies; with --noise chunks also one sampler noise per "
        "chunk) to one recorded demonstration, weights frozen, and write a complete LeRobot checkpoint that acts "
        "adapted from its first action: the base's files (weights bit for bit) plus adaptation.safetensors and "
        "adaptation.json (the demonstration, fit settings, fit error and ratio, date). Use it as any checkpoint: "
        "lerobot-eval / lerobot-rollout --policy.path=OUT; --policy.use_adaptation=false acts as the base.",
    )
    add_demonstration_arguments(p, "adapted")
    p.add_argument("--noise", choices=("none", "chunks"), default=None,
                   help="also fit one sampler noise per chunk (default: the checkpoint's fit_noise)")
    p.add_argument("--steps", type=_non_negative, default=None, help="gradient steps on z (default: fit_steps)")
    p.add_argument("--lr", type=_step_size, default=None, help="Adam step size on z (default: fit_lr)")
    p.add_argument("--seed", type=_seed, default=0, help="fitting seed (default 0)")
    p.add_argument("--device", default="cpu", help="torch device to fit on (default cpu)")
    p.set_defaults(func=cmd_adapt)


def cmd_adapt(args: argparse.Namespace) -> int:
    from lerobot_pdp.adapted import adapt_checkpoint

    out = adapt_checkpoint(args.checkpoint, (args.demo, args.episode), args.out, noise=args.noise, steps=args.steps,
                           lr=args.lr, seed=args.seed, device=args.device)
    info = json.loads((out / "adaptation.json").read_text())
    sizes = ", ".join(f"{p.name} ({p.stat().st_size / 1000:.1f} kB)" for p in sorted(out.glob("adaptation.*")))
    ratio = info.get("error_ratio")
    print(f"wrote {out}: latent {latent_text(info['latent'])}, {info['noise_chunks']} chunk noise(s), error ratio "
          f"{'n/a' if ratio is None else f'{ratio:.2f}'}{' (of the latent alone)' if info['noise_chunks'] else ''}; "
          f"adaptation files {sizes}")
    return 0


def add_search_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "search",
        help="search a PDP checkpoint's latent by outcome (success, reward, way-points) and write it adapted",
        description="Search z (one per phase for segmented policies) with CMA-ES or CEM, scoring each candidate by "
        "rollouts in a suite env: by task success, the summed reward, or --waypoints passed in order within "
        "--radius, which steers without any demonstration. With --out, writes a complete LeRobot checkpoint acting "
        "under the best latent (the base's files plus adaptation.safetensors / adaptation.json recording the "
        "search). Deterministic under --seed; Ctrl-C stops the search and keeps the best so far (written to --out; exit status 130).",
    )
    p.add_argument("checkpoint", type=Path, help="a PDP pretrained_model folder (config.json + model.safetensors)")
    _add_env_argument(p)
    p.add_argument("--scene", default="0",
                   help="scene index 0-3, a validation scene (val1, ...) or a scene file (JSON/YAML); default 0")
    p.add_argument("--waypoints", default=None,
                   help="score by way-points passed in order: a JSON/YAML file (a list of points or a scene file "
                   "with 'waypoints') or 'scene' for the scene's own")
    p.add_argument("--radius", type=float, default=WAYPOINT_RADIUS, help="a way-point counts as passed within "
                   f"this distance (metres, default {WAYPOINT_RADIUS})")
    p.add_argument("--score", choices=("success", "reward"), default=None,
                   help="without --waypoints: task success (default) or the summed reward")
    p.add_argument("--finish", action="store_true",
                   help="with --waypoints: a rollout that passes every way-point scores 1 more if it then succeeds "
                   "(the task's own success): the route, and the task done at its end")
    p.add_argument("--budget", type=int, default=200, help="rollouts in all (default 200)")
    p.add_argument("--rollouts-per-candidate", type=int, default=2, help="rollouts scoring each latent (default 2)")
    p.add_argument("--confirm-rollouts", type=int, default=None,
                   help="a latent that beats the best so far is rolled out again up to this many rollouts in all and "
                   f"replaces it only if still better; 0 for none (default {CONFIRM_ROLLOUTS})")
    p.add_argument("--method", choices=("cma", "cem"), default="cma", help="CMA-ES (default) or the cross-entropy method")
    p.add_argument("--init", choices=("modes", "adaptation"), default="modes",
                   help="start from every mode's mean latent (default), or from the latent CHECKPOINT carries (an "
                   "adapted checkpoint, e.g. from lerobot-pdp adapt)")
    p.add_argument("--seed", type=_seed, default=0,
                   help="search seed, which seeds the env's resets too: same seed, same candidates and rollouts "
                   "(default 0)")
    p.add_argument("--out", type=Path, default=None,
                   help="the adapted checkpoint folder to write (must not exist); without it nothing is written")
    p.add_argument("--history", type=Path, default=None,
                   help="also write every candidate (latent, score, success, rollouts) to this JSON file (must not exist)")
    p.add_argument("--device", default="cpu", help="torch device to act on (default cpu)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=cmd_search)


def cmd_search(args: argparse.Namespace) -> int:
    import functools
    import math

    # the arguments first: the imports below take seconds (torch, LeRobot, MuJoCo)
    for path, flag in ((args.out, "--out"), (args.history, "--history")):  # before the search, not after it
        _check_new_path(path, flag)
    if args.history is not None and not args.history.parent.is_dir():
        raise FileNotFoundError(f"--history {args.history}: folder {args.history.parent} does not exist")
    if args.out is not None and args.history is not None and args.out.resolve() == args.history.resolve():
        raise ValueError(f"--out and --history are both {args.out}: the checkpoint is a folder, the history a file")
    for flag, value in (("--budget", args.budget), ("--rollouts-per-candidate", args.rollouts_per_candidate)):
        if value < 1:
            raise ValueError(f"{flag} must be >= 1, got {value}")
    if args.finish and args.waypoints is None:
        raise ValueError("--finish adds the task's success to the way-point score: give --waypoints too")
    if args.score is not None and args.waypoints is not None:
        raise ValueError(f"--score {args.score} and --waypoints are two objectives: way-points score the route "
                         "passed (--finish adds the task's success); give one of them")
    if args.budget < args.rollouts_per_candidate:
        raise ValueError(f"--budget {args.budget} rollouts pays for no candidate of --rollouts-per-candidate "
                         f"{args.rollouts_per_candidate} rollouts")
    if args.waypoints is not None and not (math.isfinite(args.radius) and args.radius > 0):
        raise ValueError(f"--radius must be a finite number > 0 (metres), got {args.radius}")
    require_checkpoint_files(args.checkpoint)

    import gymnasium as gym

    import lerobot_pdp.envs as envs
    from lerobot_pdp.adapted import search_checkpoint
    from lerobot_pdp.atomic import write_text_atomic
    from lerobot_pdp.candidate_rollouts import check_env_features, env_camera_kwargs
    from lerobot_pdp.envs.recording import check_waypoints, resolve_waypoints
    from lerobot_pdp.envs.scene import load_scene
    from lerobot_pdp.latent_search import LatentSearchError
    from lerobot_pdp.outcome_scores import SCORES, WaypointScore

    suite = envs.get_suite_env(args.env)
    scene = load_scene(args.scene, suite.scene_key)
    objective: dict = {"env": suite.name, "scene": scene.name}
    if args.waypoints is not None:
        # a shipped scene by its name (its file's path is the installed package's, no use on another machine)
        source = f"way-points of scene {args.scene}" if args.waypoints == "scene" else args.waypoints
        points = resolve_waypoints(args.waypoints, scene, suite)
        check_waypoints(suite, points, source)
        score = WaypointScore(points, args.radius, dims=suite.trace_dims, finish=args.finish)
        objective["waypoints_from"] = str(source)
    else:
        score = SCORES[args.score or "success"]
    cfg = _checkpoint_config(args.checkpoint)
    factory = functools.partial(gym.make, suite.gym_id, scene=scene, max_episode_steps=suite.max_episode_steps,
                                disable_env_checker=True, **env_camera_kwargs(cfg))
    probe = factory()  # a checkpoint of another env: said before the policy loads and the budget is planned
    try:
        check_env_features(cfg, probe)
    except ValueError as e:
        raise ValueError(f"--env {suite.name} does not match checkpoint {args.checkpoint}: {e}") from e
    finally:
        probe.close()
    try:
        res = search_checkpoint(args.checkpoint, factory, score, out=args.out, init=args.init, device=args.device,
                                provenance=objective, budget=args.budget, method=args.method, seed=args.seed,
                                rollouts_per_candidate=args.rollouts_per_candidate, progress=not args.no_progress,
                                confirm_rollouts=CONFIRM_ROLLOUTS if args.confirm_rollouts is None else args.confirm_rollouts)
    except LatentSearchError as e:  # the candidates so far are kept where asked
        if args.history is not None:
            write_text_atomic(args.history, json.dumps(e.result.to_dict(), indent=1))
            print(f"wrote {args.history}: the {len(e.result.history)} candidates before the error")
        raise
    if args.history is not None:
        write_text_atomic(args.history, json.dumps(res.to_dict(), indent=1))
        print(f"wrote {args.history}: the {len(res.history)} candidates")
    print(f"{'interrupted: ' if res.interrupted else ''}best latent {latent_text(res.latent)}: score {res.score:.3g}, "
          f"success {100 * res.success:.0f} % of its {res.history[res.best_trace[-1][1]].rollouts} rollouts; "
          f"{len(res.history)} candidates, {res.rollouts_used} of {res.budget} rollouts in {res.seconds:.0f} s")
    if not res.interrupted and all(c.generation == 0 for c in res.history):
        print(f"the budget ended with the starting latents ({len(res.history)} of them): no {res.method} step was "
              "taken; a larger --budget lets it search beyond them")
    print(f"wrote {args.out}" if args.out is not None else "no --out: no checkpoint written")
    return 130 if res.interrupted else 0  # as Ctrl-C ends every other command, the best so far kept all the same


def _integer(minimum: int) -> Callable[[str], int]:
    """An integer flag's type, refused below ``minimum`` by the parser, which names the flag (the functions behind
    the flags would name their Python parameters, or numpy a seed, instead)."""
    def integer(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    return integer


def _number(low: float, high: float = math.inf, low_included: bool = False) -> Callable[[str], float]:
    """A float flag's type: a finite number above ``low`` (or at it, ``low_included``) and at most ``high``."""
    def number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        inside = (value >= low if low_included else value > low) and value <= high and math.isfinite(value)
        if not inside:
            bounds = f"{'>=' if low_included else '>'} {low:g}" + (f" and <= {high:g}" if math.isfinite(high) else "")
            raise argparse.ArgumentTypeError(f"must be a finite number {bounds}, got {text!r}")
        return value

    return number


_non_negative = _integer(0)
_seed = _non_negative  # numpy refuses a negative seed without naming the flag
_count = _integer(1)
_step_size = _number(0)


def _checkpoint_config(checkpoint: Path):
    from lerobot_pdp import PDPConfig
    from lerobot_pdp.checkpoint_files import check_checkpoint_source

    require_checkpoint_files(checkpoint)
    check_checkpoint_source(checkpoint)
    cfg = PDPConfig.from_pretrained(checkpoint)
    if not isinstance(cfg, PDPConfig):
        raise ValueError(f"{checkpoint} is a '{cfg.type}' checkpoint: search needs a PDP one (type 'pdp')")
    return cfg


def add_teach_parser(sub: argparse._SubParsersAction) -> None:
    from lerobot_pdp.teach_defaults import (
        TEACH_DEMO_SHARE,
        TEACH_LATENT,
        TEACH_LATENTS,
        TEACH_LR,
        TEACH_STEPS,
    )

    p = sub.add_parser(
        "teach",
        help="teach a PDP checkpoint one demonstration as a new mode and write the taught checkpoint",
        description="For a route no latent makes (the fit's error ratio warns of it): add the demonstration to the "
        "policy as a new mode. The encoder stays as trained, so the old modes keep their latents; the new mode's "
        "latent is the encoder's mean of the demonstration; the denoiser is fine-tuned with a share of each batch "
        "from the demonstration and the rest rehearsing the training data. Writes a complete LeRobot checkpoint "
        "(config naming the new mode, weights, processors, teaching.json, model card); steer to the new mode with "
        "--policy.steer_mode=<id>. With --taught-from instead of --demo: teach the checkpoint every mode a taught "
        "checkpoint was taught, from the demonstrations it keeps (where lerobot-train dropped them: another dataset whose "
        "modes take their ids, or --policy.taught_rehearsal_share=0).",
    )
    add_demonstration_arguments(p, "taught", demo_required=False,
                                episode_help="its episode index (default 0); several: one new mode each, taught in "
                                "order into one checkpoint, e.g. the routes one lerobot-record session recorded")
    p.add_argument("--taught-from", type=Path, default=None,
                   help="a taught checkpoint: teach every mode it was taught, in order and under its name, from the "
                   "demonstrations it keeps (instead of --demo; e.g. onto a checkpoint lerobot-train trained without them)")
    p.add_argument("--data", type=Path, default=None,
                   help="the dataset the checkpoint was trained on, rehearsed while teaching (default: the one its "
                   "train_config.json names)")
    p.add_argument("--name", nargs="+", default=None,
                   help="the new mode's name, one per --episode (default: where the demonstration came from)")
    p.add_argument("--steps", type=_count, default=TEACH_STEPS,
                   help=f"fine-tuning steps, per new mode (default {TEACH_STEPS})")
    p.add_argument("--lr", type=_step_size, default=TEACH_LR, help=f"their Adam step size (default {TEACH_LR:g})")
    p.add_argument("--demo-share", type=_number(0, 1), default=TEACH_DEMO_SHARE,
                   help=f"the demonstration's share of each batch (default {TEACH_DEMO_SHARE:g})")
    p.add_argument("--latent", choices=TEACH_LATENTS, default=TEACH_LATENT,
                   help="the new mode's latent: the encoder's mean of the demonstration, or where the latent "
                   f"geometry puts it against the training latents (default {TEACH_LATENT})")
    p.add_argument("--seed", type=_seed, default=0, help="seed (default 0)")
    p.add_argument("--device", default="cpu", help="torch device to fine-tune on (default cpu)")
    p.set_defaults(func=cmd_teach)


def _check_teach_args(args: argparse.Namespace) -> None:
    """What ``teach`` would refuse after seconds of loading, refused at once (torch-free)."""
    from lerobot_pdp.episodes import recording_info
    from lerobot_pdp.teach_defaults import check_mode_name, check_teach_settings

    check_teach_settings(args.steps, args.lr, args.demo_share)
    for name in args.name or []:
        check_mode_name(name)
    require_checkpoint_files(args.checkpoint)
    require_new_folder(args.out, "taught", args.checkpoint)
    if args.demo is not None:
        recording_info(args.demo)  # a missing or unfinished recording, named
    if args.taught_from is not None:
        require_checkpoint_files(args.taught_from)


def cmd_teach(args: argparse.Namespace) -> int:
    if (args.demo is None) == (args.taught_from is None):
        raise ValueError("give the demonstration with --demo, or a taught checkpoint whose modes to teach again with "
                         "--taught-from (one of them)")
    if args.taught_from is not None and args.name is not None:
        raise ValueError("--name names a --demo's mode; --taught-from keeps the taught modes' names")
    if args.name is not None and len(args.name) != len(args.episode):
        raise ValueError(f"--name gives {len(args.name)} name(s) for {len(args.episode)} --episode(s): one per "
                         "episode, or none")
    if len(set(args.episode)) != len(args.episode):
        raise ValueError(f"--episode {' '.join(map(str, args.episode))} repeats an episode")
    _check_teach_args(args)
    # torch and LeRobot are imported after the argument checks
    from lerobot_pdp.taught import teach_again_from, teach_checkpoint_modes

    if args.taught_from is not None:
        out, done = teach_again_from(args.checkpoint, args.taught_from, args.out, training_data=args.data,
                                     steps=args.steps, lr=args.lr, demo_share=args.demo_share, seed=args.seed,
                                     latent=args.latent, device=args.device)
        for old, res in done:
            print(f"mode {old} of {args.taught_from} -> mode {res.mode}, latent {latent_text(res.z)}, {res.steps} steps in "
                  f"{res.seconds:.0f} s")
        ids = ", ".join(str(res.mode) for _, res in done)
        print(f"wrote {out}: {len(done)} taught mode(s), {ids}; steer with --policy.steer_mode=<one of them>")
        return 0
    out, done = teach_checkpoint_modes(args.checkpoint, [(args.demo, ep) for ep in args.episode], args.out,
                                       training_data=args.data, steps=args.steps, lr=args.lr,
                                       demo_share=args.demo_share, seed=args.seed, names=args.name,
                                       latent=args.latent, device=args.device)
    for ep, res in zip(args.episode, done, strict=True):
        print(f"{'episode ' + str(ep) + ': ' if len(done) > 1 else ''}mode {res.mode}, latent {latent_text(res.z)} "
              f"({res.nearest_spreads:.1f} spreads from the nearest training latent), {res.steps} steps in "
              f"{res.seconds:.0f} s")
    print("(a spread: the training latents' RMS standard deviation per dim; a new route sharing most of its path "
          "with a training one lands near that one's latent)")
    steer = str(done[0].mode) if len(done) == 1 else "<id>"
    print(f"wrote {out}: taught mode(s) {', '.join(str(res.mode) for res in done)}; steer with "
          f"--policy.steer_mode={steer}")
    return 0


# ---- explore --------------------------------------------------------------------------------------


def add_explore_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "explore",
        help="open a checkpoint in the explorer, a local web app: latent map, rollouts per clicked latent, ...",
        description="Serve a local web app (Gradio; pip install the 'explore' extra) on a PDP checkpoint: its latent "
        "map with the training behaviors; a click on it rolls the policy out from that latent in --scene (success, "
        "collisions); interpolation between two modes; a demonstration fitted and marked on the map with its error "
        "ratio; the success landscape over z (cached); the chosen latent saved as an adapted checkpoint. Without "
        "--env (a real robot's checkpoint): the map and the decoder's view of a latent instead of rollouts.",
    )
    p.add_argument("checkpoint", type=Path, help="a PDP pretrained_model folder (config.json + model.safetensors)")
    p.add_argument("--env", default=None,
                   help=f"suite env to roll out in, one of {', '.join(_env_names())} (default: none, no rollouts)")
    p.add_argument("--scene", default="0",
                   help="scene index 0-3, a validation scene (val1, ...) or a scene file (JSON/YAML); default 0")
    p.add_argument("--rollouts", type=_int_in(1), default=8, help="rollouts per selected latent (default 8)")
    p.add_argument("--max-steps", type=_int_in(1), default=None,
                   help="steps per rollout (default: the env's time limit)")
    p.add_argument("--dataset", type=Path, default=None,
                   help="a LeRobotDataset for demonstrations and the decoder's view (default: the training dataset "
                   "train_config.json names, when it is on this machine)")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="where success landscapes are cached (default $LEROBOT_PDP_CACHE/explorer, else "
                   "~/.cache/lerobot_pdp/explorer)")
    p.add_argument("--port", type=_int_in(1, 65535), default=7860, help="local port (default 7860)")
    p.add_argument("--share", choices=("true", "false"), default="false",
                   help="also a public Gradio share link (default false)")
    p.add_argument("--device", default="cpu", help="torch device to act on (default cpu)")
    p.add_argument("--k", type=_int_in(1), default=None,
                   help="without mode labels: the number of modes to group the training episodes in (default: "
                   "found by policy.discover_modes(); one per episode below six episodes); labels, where the data "
                   "has them, win")
    p.set_defaults(func=cmd_explore)


def _int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an int in [low, high], else argparse's error naming the flag and the range (before
    seconds of loading)."""
    def parse(text: str) -> int:
        value = int(text)
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {low}..{high}, got {value}" if high is not None
                                             else f"must be >= {low}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse's "invalid integer value: 'x'" for text that is no int
    return parse


def cmd_explore(args: argparse.Namespace) -> int:
    from lerobot_pdp.explorer import Explorer, import_gradio
    from lerobot_pdp.explorer_app import launch

    try:  # before loading anything: a missing optional dependency is the first thing said
        import_gradio()
    except ImportError as e:
        raise RuntimeError(str(e)) from e
    import socket

    from lerobot_pdp.explorer import check_checkpoint_folder

    check_checkpoint_folder(args.checkpoint)  # a mistyped folder: said first (no port or loading involved)
    with socket.socket() as probe:  # a taken port, before minutes of loading and Gradio's traceback
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is free
        try:
            probe.bind(("127.0.0.1", args.port))
        except OSError as e:
            raise RuntimeError(f"port {args.port} is not free ({e.strerror}): another explorer or program holds "
                               "it; give another with --port") from None
    explorer = Explorer(args.checkpoint, env=args.env, scene=args.scene, rollouts=args.rollouts,
                        max_steps=args.max_steps, cache_dir=args.cache_dir, dataset=args.dataset, device=args.device,
                        k=args.k)
    print(f"explorer on {args.checkpoint}: http://127.0.0.1:{args.port} (Ctrl-C stops it)")
    launch(explorer, port=args.port, share=args.share == "true")
    return 0


# ---- benchmark -------------------------------------------------------------------------------------


def add_benchmark_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "benchmark",
        help="the paper's evaluation protocol: train PDP and baselines, evaluate scenes 0-3",
        description="Generate (or reuse) the scene-0 dataset, train every method with lerobot-train, evaluate "
        "scene 0 (per-mode latents) and scenes 1-3 (adapted to one demonstration; with --split validation the "
        "env's validation scenes instead), write results.json, results.md and figures/. Finished (method, seed) "
        "runs are reused.",
    )
    _add_env_argument(p)
    p.add_argument("--out", required=True, type=Path, help="output folder (reused to resume)")
    # None = not given: the defaults depend on --quick (resolved in cmd_benchmark)
    p.add_argument("--seeds", type=int, nargs="+", default=None,
                   help="training seeds (default 0 1 2, with --split validation 100 101 102; the first with --quick)")
    p.add_argument("--rollouts", type=int, default=None, help="rollouts per scene (default 40; 20 with --quick)")
    p.add_argument("--methods", nargs="+", default=None,
                   help="pdp dp bc and/or ablations pdp_unaligned pdp_onehot pdp_concat pdp_input pdp_uncond; vqbet with "
                   "--obs images (default pdp dp bc; pdp dp with --quick; pdp dp vqbet with --obs images)")
    p.add_argument("--quick", action="store_true",
                   help="small budget for a first look: one seed, PDP + DP, shorter training, 20 rollouts")
    p.add_argument("--ablations", action="store_true",
                   help="also the paper's ablations and the warm/random initialisation table")
    p.add_argument("--steps", type=int, default=None, help="override the env's training steps")
    p.add_argument("--lr", type=float, default=None,
                   help="override the env's learning rate (every method and network alike)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="override the env's training batch size (every method alike)")
    p.add_argument("--episodes-per-mode", type=int, default=None,
                   help="override the env's demonstrations per mode in the scene-0 dataset")
    p.add_argument("--split", choices=("test", "validation"), default="test",
                   help="test (default): scene 0 and test scenes 1-3; validation: scene 0 and the env's validation "
                   "scenes (val1, val2, ...) on validation seeds, where settings are chosen")
    p.add_argument("--scenes", nargs="+", default=None,
                   help="scenes to evaluate: indices and/or validation scene names (default: those of --split)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--inference-steps", type=int, default=None,
                   help="DDIM steps of PDP and DP (default: each method's validated setting, settings.FROZEN, else "
                   "the env's); re-evaluates cached runs made with other steps, without retraining")
    p.add_argument("--timestep-spacing", choices=("leading", "trailing", "even"), default=None,
                   help="DDIM grid of PDP's and DP's shared sampler (default as --inference-steps); 'even' is "
                   "PDP's own sampler, without dp; re-evaluates like --inference-steps")
    p.add_argument("--validate", action="store_true",
                   help="with --split validation: evaluate every method's candidate samplers and adaptation "
                   "settings (lerobot_pdp/benchmark/validation.py) and write validation.json / validation.md")
    p.add_argument("--jobs", type=int, default=1,
                   help="with --validate: processes evaluating the candidates of a stage side by side (default 1)")
    p.add_argument("--reuse-validation", type=Path, default=None,
                   help="with --validate: an earlier validation.json of this env whose candidates are not evaluated "
                   "again where the retrained runs reproduce its rollouts exactly (then only new candidates run)")
    p.add_argument("--teach", action="store_true",
                   help="also teach each method the route of the split's zero-mode scenes (PDP: teach, a new mode; "
                   "BC / DP: fine-tuned with the same rehearsal) and measure the new route and what scene 0 kept; "
                   "writes teach.json / teach.md")
    p.add_argument("--device", default="cpu",
                   help="torch device every method trains, adapts and acts on: cpu (default), cuda, cuda:1 ...")
    p.add_argument("--film", choices=("mlp", "affine"), default=None,
                   help="PDP's FiLM form, z -> (gamma, beta) through the paper's [16, 32] MLP or one linear layer "
                   "(default: the env's, settings.FILM: affine on pick-place, mlp elsewhere); a training setting, "
                   "compared on --split validation")
    p.add_argument("--rec-reduction", choices=("mean", "sum"), default="mean",
                   help="how PDP's L_rec reduces a trace's squared error: mean over its elements (default) or the "
                   "paper's sum; a training setting, compared on --split validation")
    p.add_argument("--obs", choices=("state", "images"), default="state",
                   help="images: the camera variant - datasets, policies and rollouts observe one camera "
                   "(observation.images.<camera>) besides the state; methods pdp, dp and vqbet (default state)")
    p.add_argument("--camera", default=None,
                   help="camera of --obs images (default: the env's benchmark camera, e.g. oblique on reach-around)")
    p.add_argument("--image-size", type=int, default=None, help="camera image size with --obs images (default 64)")
    p.set_defaults(func=cmd_benchmark)


def benchmark_config(args: argparse.Namespace) -> BenchmarkConfig:
    """The ``BenchmarkConfig`` of parsed ``benchmark`` arguments: --quick changes the defaults of seeds,
    rollouts and methods, --split those of scenes and seeds, never a value given explicitly."""
    from lerobot_pdp.benchmark.settings import BenchmarkConfig, split_scenes, split_seeds

    seeds = args.seeds if args.seeds is not None else split_seeds(args.split, args.quick)
    if args.scenes is None and args.split == "test":
        scenes = split_scenes(args.env, "test")
    elif args.scenes is None:
        import lerobot_pdp.envs as envs  # registers the suite, so --env may be any of an env's names

        scenes = split_scenes(envs.get_suite_env(args.env).name, args.split)
    else:
        scenes = tuple(int(s) if s.strip().lstrip("-").isdigit() else s.strip() for s in args.scenes)
    rollouts = args.rollouts if args.rollouts is not None else 20 if args.quick else 40
    methods = (args.methods if args.methods is not None else ["pdp", "dp", "vqbet"] if args.obs == "images"
               else ["pdp", "dp"] if args.quick else ["pdp", "dp", "bc"])
    if args.obs == "state" and (args.camera is not None or args.image_size is not None):
        raise SystemExit("--camera / --image-size need --obs images")
    camera = {"obs": args.obs, "camera": args.camera}
    if args.image_size is not None:
        camera["image_size"] = args.image_size
    return BenchmarkConfig(env=args.env, out=args.out, seeds=seeds, rollouts=rollouts, methods=methods,
                           quick=args.quick, ablations=args.ablations, scenes=scenes, split=args.split, steps=args.steps,
                           lr=args.lr, batch_size=args.batch_size, episodes_per_mode=args.episodes_per_mode, inference_steps=args.inference_steps,
                           timestep_spacing=args.timestep_spacing, validate=args.validate,
                           figures=not args.no_figures, device=args.device, jobs=args.jobs, film=args.film,
                           rec_reduction=args.rec_reduction,
                           reuse_validation=args.reuse_validation, teach=args.teach,
                           **camera)


def cmd_benchmark(args: argparse.Namespace) -> int:
    from lerobot_pdp.benchmark.protocol import run_benchmark

    res = run_benchmark(benchmark_config(args))
    print()
    print((Path(args.out) / "results.md").read_text())
    print(f"results: {Path(args.out) / 'results.json'} and {Path(args.out) / 'results.md'}")
    for f in res.get("figures", []):
        print(f"figure:  {Path(args.out) / f}")  # results.json keeps it relative to the output folder
    return 0


def add_search_curves_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "search-curves",
        help="success against search rollouts on one shifted scene of a trained benchmark run",
        description="On a benchmark output folder's trained runs (runs/pdp/seed<k>, runs/dp/seed<k>): CMA-ES over "
        "PDP's latent from the gradient fit (z_fit) and from the mode means (z_modes), the gradient fit alone (fit) "
        "and CMA-ES over LeRobot diffusion's initial noise with the same budget (dp_noise). Each budget runs its own "
        "search (with --confirm-rollouts 0: one search per method at the largest budget, read at each budget); the "
        "best candidate at each budget is evaluated on the protocol's evaluation rollouts of the scene (seeds the "
        "search never used). Writes search_curves.json / .md / .png in --out; "
        "finished (method, scene, seed) records are reused.",
    )
    p.add_argument("results", type=Path, help="a benchmark output folder (runs/<method>/seed<k>/pretrained_model)")
    _add_env_argument(p)
    p.add_argument("--scene", required=True, help="a shifted scene: 1-3 (test) or val1, val2, ... (validation)")
    p.add_argument("--seed", type=int, required=True, help="the training seed of the runs (e.g. 100)")
    p.add_argument("--budgets", type=int, nargs="+", default=[16, 32, 64, 128, 256, 512],
                   help="search rollouts at which the curve is read (default 16 32 64 128 256 512)")
    p.add_argument("--rollouts", type=int, default=40, help="evaluation rollouts per point (default 40)")
    p.add_argument("--rollouts-per-candidate", type=int, default=2,
                   help="search rollouts scoring each candidate (default 2)")
    p.add_argument("--confirm-rollouts", type=int, default=None,
                   help="rollouts in all before a candidate replaces the search's best, 0 for none (default: the "
                   f"search's own, {CONFIRM_ROLLOUTS}); with confirmation each budget runs its own search")
    p.add_argument("--score", choices=("success", "waypoints", "waypoints_finish"), default="success",
                   help="what the searches maximise: task success (default), the scene's way-points passed in "
                   "order, or those way-points and then the task's success (waypoints_finish); no demonstration "
                   "with way-points: z_modes and dp_noise only")
    p.add_argument("--finish", action="store_true",
                   help="with --score waypoints: the way-points and then the task's success, as `lerobot-pdp search "
                   "--finish` (the same as --score waypoints_finish)")
    p.add_argument("--radius", type=float, default=WAYPOINT_RADIUS, help="with way-points: pass radius (default 0.05)")
    p.add_argument("--methods", nargs="+", default=None,
                   help="any of z_fit z_modes fit dp_noise (default: all that --score allows)")
    p.add_argument("--dp-results", type=Path, default=None,
                   help="the benchmark output folder holding runs/dp/seed<k>, where not RESULTS")
    p.add_argument("--device", default="cpu", help="torch device to act on (default cpu)")
    p.add_argument("--out", required=True, type=Path, help="folder for search_curves.json / .md / .png (reused)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=cmd_search_curves)


def cmd_search_curves(args: argparse.Namespace) -> int:
    from lerobot_pdp.benchmark.search_curves import RECORD, TABLE, run_search_curves

    if args.finish:  # one spelling with `lerobot-pdp search --finish`; records keep the score's name
        if args.score not in ("waypoints", "waypoints_finish"):
            raise ValueError(f"--finish adds the task's success to the way-point score: use it with --score waypoints, "
                             f"not --score {args.score}")
        args.score = "waypoints_finish"
    scene = int(args.scene) if args.scene.strip().isdigit() else args.scene.strip()
    # the command as the record keeps it: a folder given by an absolute path by its name (records get committed)
    results = args.results.name if args.results.is_absolute() else str(args.results)
    argv = ["lerobot-pdp search-curves", results, "--env", args.env, "--scene", str(scene), "--seed",
            str(args.seed), "--budgets", *map(str, args.budgets), "--rollouts", str(args.rollouts),
            "--rollouts-per-candidate", str(args.rollouts_per_candidate), "--score", args.score]
    confirm = CONFIRM_ROLLOUTS if args.confirm_rollouts is None else args.confirm_rollouts
    argv += ["--confirm-rollouts", str(confirm)]
    if args.score != "success":
        argv += ["--radius", f"{args.radius:g}"]
    if args.methods:
        argv += ["--methods", *args.methods]
    if args.dp_results is not None:
        argv += ["--dp-results", args.dp_results.name if args.dp_results.is_absolute() else str(args.dp_results)]
    run_search_curves(args.results, args.env, scene, args.seed, args.out, budgets=args.budgets, rollouts=args.rollouts,
                      score=args.score, methods=args.methods, radius=args.radius,
                      rollouts_per_candidate=args.rollouts_per_candidate, dp_out=args.dp_results, device=args.device,
                      confirm_rollouts=confirm, progress=not args.no_progress, command=" ".join(argv))
    print((args.out / TABLE).read_text())
    print(f"wrote {args.out / RECORD}, {args.out / TABLE} and the curve search_curves.png")
    return 0


def add_merge_results_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "merge-results",
        help="one results table from benchmark runs of different seeds",
        description="Merge the results.json of benchmark runs that used the same env and settings but different "
        "seeds (or methods), e.g. seeds run on several machines. Writes OUT/results.json and OUT/results.md; runs "
        "with --teach also get one OUT/teach.json / teach.md; validation runs (--split validation --validate, one "
        "method per folder) also get one merged OUT/validation.json / validation.md.",
    )
    p.add_argument("results", type=Path, nargs="+", help="benchmark output folders or their results.json files")
    p.add_argument("--out", required=True, type=Path, help="folder for the merged results.json / results.md")
    p.set_defaults(func=cmd_merge_results)


def cmd_merge_results(args: argparse.Namespace) -> int:
    from lerobot_pdp.atomic import write_text_atomic
    from lerobot_pdp.benchmark.results import merge_results, results_markdown

    files = [r / "results.json" if r.is_dir() else r for r in args.results]
    for f in files:
        if not f.is_file():
            raise FileNotFoundError(f"no results file at {f} (give a benchmark --out folder or its results.json)")
    target = args.out / "results.json"
    if any(target.resolve() == f.resolve() for f in files):
        raise ValueError(f"--out {args.out} would overwrite one of the inputs ({target}); choose another folder")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} is a file; give a folder for the merged results")
    if (args.out / "runs").is_dir() or (target.is_file() and "merged_from" not in _json_or_empty(target)):
        raise ValueError(f"--out {args.out} holds a benchmark run (its own results.json and runs/), not an earlier "
                         "merge: merging into it would replace its records; choose a new folder")
    run = next((p for p in args.out.resolve().parents if (p / "runs").is_dir() and (p / "results.json").is_file()),
               None)
    if run is not None:
        raise ValueError(f"--out {args.out} lies inside the benchmark run {run}: a merge goes in a folder of its own")
    loaded = []
    for f in files:
        try:
            loaded.append((str(f), json.loads(f.read_text())))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:  # a text that is no JSON, or no text at all
            raise ValueError(f"{f} is not JSON ({e})") from e
    res = merge_results(loaded)
    # named relative to the merged folder: the merged results.json records where its parts came from
    res["merged_from"] = [os.path.relpath(f, args.out) for f in files]
    table = results_markdown(res)  # everything computed before anything is written
    # validation runs, one per method: their validation.json records are merged too
    records = [f.with_name("validation.json") for f in files]
    merged_validation = None
    if res.get("split") == "validation" and all(r.is_file() for r in records):
        from lerobot_pdp.benchmark.validation import merge_validation_records, validation_markdown

        merged_validation = merge_validation_records([(str(r), json.loads(r.read_text())) for r in records])
    elif res.get("split") == "validation" and any(r.is_file() for r in records):
        missing = [str(r) for r in records if not r.is_file()]
        print(f"validation records not merged: no {', '.join(missing)} (runs without --validate)")
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(target, json.dumps(res, indent=1))
    write_text_atomic(args.out / "results.md", table)
    if "teach" in res:  # runs with --teach: their teaching records as one teach.json / teach.md
        from lerobot_pdp.benchmark.teaching import teach_markdown

        write_text_atomic(args.out / "teach.json", json.dumps(res["teach"], indent=1))
        write_text_atomic(args.out / "teach.md", teach_markdown(res["teach"]))
        print(f"teaching record: {args.out / 'teach.json'} ({', '.join(res['teach']['runs'])})")
    if merged_validation is not None:
        write_text_atomic(args.out / "validation.json", json.dumps(merged_validation, indent=1))
        write_text_atomic(args.out / "validation.md", validation_markdown(merged_validation))
        print(f"validation record: {args.out / 'validation.json'} ({', '.join(merged_validation['methods'])})")
    # an earlier merge into this folder: its records this merge does not rewrite describe other runs
    kept = {"teach": "teach" in res, "validation": merged_validation is not None}
    stale = [args.out / f"{name}.{ext}" for name, ok in kept.items() if not ok for ext in ("json", "md")]
    for f in [f for f in stale if f.is_file()]:
        f.unlink()
        print(f"removed {f}: it recorded runs this merge does not hold")
    print(table)
    print(f"results: {target} and {args.out / 'results.md'}")
    return 0


def _json_or_empty(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [
    add_make_dataset_parser,
    add_plot_dataset_parser,
    add_label_modes_parser,
    add_latent_map_parser,
    add_steer_parser,
    add_adapt_parser,
    add_search_parser,
    add_teach_parser,
    add_explore_parser,
    add_benchmark_parser,
    add_search_curves_parser,
    add_merge_results_parser,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lerobot-pdp", allow_abbrev=False,
        description="Parameterized Diffusion Policy tools beside LeRobot's CLIs: datasets, benchmark, steering, "
                    "adaptation, teaching")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in SUBCOMMANDS:
        add(sub)
    for command in sub.choices.values():  # a mistyped flag (--step for --steps) is an error, not taken as a prefix
        command.allow_abbrev = False
        command.set_defaults(_parser=command)  # an unknown flag is named by its subcommand (see main)
    return parser


def _unknown_arguments(parser: argparse.ArgumentParser, extra: list[str]) -> None:
    """Exit naming the subcommand's usage and, for a mistyped flag, the nearest it has (argparse names the
    top-level usage instead, which lists no flag)."""
    import difflib

    flags = [f for action in parser._actions for f in action.option_strings if f.startswith("--")]

    def nearest(given: str) -> str | None:
        stem = [f for f in flags if f.startswith(given) or given.startswith(f)]  # --episodes: --episodes-per-mode
        return (stem or difflib.get_close_matches(given, flags, n=1, cutoff=0.75) or [None])[0]

    given = [x.partition("=")[0] for x in extra if x.startswith("--")]
    hints = [f"{x}: did you mean {near}?" for x in given if (near := nearest(x)) is not None]
    parser.error(f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(hints)})" if hints else ""))


def main(argv: Sequence[str] | None = None) -> int:
    args, extra = build_parser().parse_known_args(argv)
    if extra:
        _unknown_arguments(args._parser, extra)
    try:
        return int(args.func(args) or 0)
    except (ValueError, KeyError, OSError, RuntimeError) as e:
        # Expected user errors (bad scene, existing output, infeasible mode) and the file system's (a read-only
        # or missing place, a file where a folder goes: OSError names the path): one clear line, no traceback.
        # One raised elsewhere (inside torch, say) says how to see where; LEROBOT_PDP_TRACEBACK=1 shows every one.
        from lerobot_pdp.cli_errors import TRACEBACK_ENV, raised_in_pdp

        if os.environ.get(TRACEBACK_ENV) == "1":
            raise
        msg = str(e.args[0] if isinstance(e, KeyError) and e.args else e).removeprefix(f"{args.command}: ")
        print(f"lerobot-pdp {args.command}: error: {msg}", file=sys.stderr)
        if not isinstance(e, OSError) and not raised_in_pdp(e.__traceback__) and not (
                e.__cause__ is not None and raised_in_pdp(e.__cause__.__traceback__)):
            print(f"({type(e).__name__} not raised by lerobot-pdp's own checks; {TRACEBACK_ENV}=1 shows the "
                  "traceback)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: a line, not torch's traceback (outputs go through atomic.py's staging)
        print(f"lerobot-pdp {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
