"""Which LeRobot program this process runs, and what its command line asks that PDP must follow: the episodes and
eval split ``lerobot-train`` trains on (command line or ``--config_path`` file, as LeRobot's parser reads them),
the ``--policy.<field>`` options given, ``lerobot-rollout``'s RTC inference. Torch-free."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any


def lerobot_program(argv: list[str] | None = None) -> str:
    """The program ``argv`` (default: this process's) runs, as its console script is named: ``lerobot-train`` also
    for ``python lerobot_train.py``; "" when unknown."""
    argv = sys.argv if argv is None else argv
    return Path(argv[0]).stem.replace("_", "-") if argv and argv[0] else ""


def command_line_value(argv: list[str], option: str) -> str | None:
    """The raw value of ``--option`` (``--option=v`` or ``--option v``) on ``argv``'s command line, as LeRobot's
    parser reads it; None when not given."""
    from lerobot.configs.parser import parse_arg

    return parse_arg(option, argv[1:])


def given_policy_fields(argv: list[str] | None = None) -> set[str]:
    """The policy fields the command line sets (``--policy.<field>=...``)."""
    argv = sys.argv if argv is None else argv
    return {a.partition("=")[0].removeprefix("--policy.") for a in argv[1:] if a.startswith("--policy.")}


def rollout_with_rtc(argv: list[str] | None = None) -> bool:
    """This process is ``lerobot-rollout --inference.type=rtc``."""
    argv = sys.argv if argv is None else argv
    args = argv[1:]
    return lerobot_program(argv) == "lerobot-rollout" and (
        "--inference.type=rtc" in args or any(a == "--inference.type" and b == "rtc"
                                               for a, b in zip(args, args[1:], strict=False)))


def running_lerobot_train(argv: list[str]) -> bool:
    """This process is ``lerobot-train`` (also each process ``accelerate launch`` starts for it)."""
    return lerobot_program(argv) == "lerobot-train"


def lerobot_train_episodes(argv: list[str]) -> list[int] | None:
    """``--dataset.episodes`` of a ``lerobot-train`` command line, else ``dataset.episodes`` of its
    ``--config_path`` file (a ``train_config.json``, its folder, or a YAML/JSON file, as LeRobot reads it); the
    command line wins, as in LeRobot's parser. None: not given, a Hub config (not read here), or another program."""
    if not running_lerobot_train(argv):
        return None
    import yaml  # draccus parses its command-line values as YAML

    given = command_line_value(argv, "dataset.episodes")
    if given is not None:
        return _episode_list(yaml.safe_load(given) if given.strip() else None, f"--dataset.episodes={given}")
    path, value = _config_file_value(argv, ("dataset", "episodes"))
    return _episode_list(value, f"{path}: dataset.episodes={value}")


def train_value(argv: list[str], flag: str, keys: tuple[str, ...]) -> Any:
    """A lerobot-train setting as LeRobot's parser sees it: the command line's ``flag``, else the ``--config_path``
    file's ``keys``; None when neither gives it."""
    import yaml

    given = command_line_value(argv, flag.removeprefix("--"))
    if given is not None:
        return yaml.safe_load(given) if given.strip() else None
    return _config_file_value(argv, keys)[1]


def _config_file_value(argv: list[str], keys: tuple[str, ...]) -> tuple[Path | None, Any]:
    """(the file, the value at ``keys``) of lerobot-train's ``--config_path`` (a ``train_config.json``, its folder,
    or a YAML/JSON file, as LeRobot reads it); (None, None) without one or for a Hub config (not read here)."""
    import yaml  # draccus reads config files as YAML/JSON

    config_path = command_line_value(argv, "config_path")
    if not config_path:
        return None, None
    path = Path(config_path)
    if path.is_dir():
        path = path / "train_config.json"
    if not path.is_file():
        return None, None
    try:
        value = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"{path}: cannot read --config_path ({e})") from e
    for key in keys:
        value = value.get(key) if isinstance(value, dict) else None
    return path, value


def _episode_list(parsed, where: str) -> list[int] | None:
    if parsed is None:
        return None
    if not isinstance(parsed, list) or not all(isinstance(e, int) and not isinstance(e, bool) for e in parsed):
        raise ValueError(f"{where}: expected a list of episode indices, e.g. '[0,2,5]'")
    return [int(e) for e in parsed]
