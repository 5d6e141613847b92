"""PDP's own error messages end LeRobot's commands as one line, not under a 200-line traceback.

``lerobot-train``, ``lerobot-eval``, ``lerobot-rollout`` and ``lerobot-record`` let an exception run out of
``main``, so a message PDP wrote for the user (``steer_mode 42 is not a mode of this checkpoint; its modes are
0 (left), ...``, a recording that lacks a camera, trace_dims past the state's size) comes last, after the
traceback through LeRobot's, draccus' and PDP's frames. ``install()`` (run by the plugin module those commands
import first) puts a ``sys.excepthook`` in front of Python's: an exception *raised on purpose by PDP* (the
innermost frame is a ``raise`` statement in PDP's code, and it is one of the error types PDP raises for bad
input) prints ``lerobot-eval: error: <message>`` and a line on how to see the traceback, with exit status 1 as
before; such an error LeRobot caught and raised again in its own (``Error creating robot with config
PDPSimConfig(<every field>): <PDP's message>``) prints PDP's message alone. Two of LeRobot's own end so too:
"config.json not found in DIR" for a folder in its training layout (``checkpoints/last``) says where the checkpoint
is below it, and a ``lerobot-train`` failing with ``--dataset.root`` where no dataset is says that (LeRobot's last
words are a network error). Everything else, PDP's bugs included (an error raised inside a library or by an
expression in PDP's code), keeps Python's traceback, and ``LEROBOT_PDP_TRACEBACK=1`` keeps it for every error.
"""

from __future__ import annotations

import contextlib
import linecache
import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

TRACEBACK_ENV = "LEROBOT_PDP_TRACEBACK"
# the errors PDP raises for bad input (files, keys, shapes, values, types): never a bug's own type
USER_ERRORS = (ValueError, KeyError, TypeError, FileNotFoundError, FileExistsError, NotADirectoryError,
               IsADirectoryError)
# how LeRobot's PreTrainedConfig.from_pretrained refuses a local folder without config.json (LeRobot 0.6.1)
LEROBOT_NO_CONFIG = "config.json not found in "
_PACKAGE = Path(__file__).resolve().parent  # lerobot_pdp: the envs, robots and teleoperators live below it


def raised_in_pdp(tb: TracebackType | None) -> bool:
    """Whether a traceback's innermost frame is a ``raise`` statement in PDP's code (an error a library or an
    expression raised has another innermost frame or line)."""
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    path = Path(tb.tb_frame.f_code.co_filename).resolve()
    return path.is_relative_to(_PACKAGE) and linecache.getline(str(path), tb.tb_lineno).lstrip().startswith("raise ")


def raised_by_pdp(error: BaseException, tb: TracebackType | None) -> bool:
    """Whether ``error`` is a message PDP raised on purpose: a user-error type raised by PDP (:func:`raised_in_pdp`)."""
    return isinstance(error, USER_ERRORS) and raised_in_pdp(tb)


def pdp_message(error: BaseException, tb: TracebackType | None) -> BaseException | None:
    """The error PDP raised on purpose that ``error`` is, or that LeRobot wrapped into ``error`` (``raise ... from``
    it, a user-error type itself); None otherwise."""
    if raised_by_pdp(error, tb):
        return error
    cause = error.__cause__
    if isinstance(error, USER_ERRORS) and cause is not None and raised_by_pdp(cause, cause.__traceback__):
        return cause
    return None


def layout_message(error: BaseException) -> str | None:
    """LeRobot's own "config.json not found in FOLDER" for a folder in its training layout (``--policy.path=
    .../checkpoints/last``, whose ``pretrained_model`` holds the checkpoint): the message with where it is."""
    from .checkpoint_files import layout_hint

    said = str(error)
    if not isinstance(error, FileNotFoundError) or not said.startswith(LEROBOT_NO_CONFIG):
        return None
    hint = layout_hint(Path(said.removeprefix(LEROBOT_NO_CONFIG)))
    return said + hint if hint else None


def dataset_message(argv: list[str]) -> str | None:
    """``lerobot-train --dataset.root=DIR`` where no LeRobotDataset is: LeRobot then asks the Hub for the repo id
    and fails with a network error (offline: "Cannot reach https://huggingface.co/api/datasets/local/...") two
    tracebacks below the missing file. Says what is missing and how a dataset is made. (Not lerobot-record's: its
    root is where it writes.)"""
    roots = [a.split("=", 1)[1] for a in argv if a.startswith("--dataset.root=")]
    if not argv or Path(argv[0]).name != "lerobot-train" or not roots:
        return None
    info = Path(roots[-1], "meta", "info.json")
    if info.is_file():
        return _missing_episodes_message(argv, roots[-1], info)
    return (f"no LeRobotDataset at --dataset.root={roots[-1]} (no meta/info.json there), so LeRobot looked for the "
            "--dataset.repo_id on the Hub instead; make the dataset first (lerobot-pdp make-dataset --out DIR, or "
            "lerobot-record) or fix the path")


def _missing_episodes_message(argv: list[str], root: str, info: Path) -> str | None:
    """``--dataset.episodes`` listing episodes the local dataset lacks: LeRobot, not finding their files, asks the
    Hub for them (offline: ``OfflineModeIsEnabled``, a traceback that names neither the episodes nor the folder)."""
    import json

    from .lerobot_command import lerobot_train_episodes

    try:
        total = int(json.loads(info.read_text()).get("total_episodes") or 0)
        episodes = lerobot_train_episodes(argv) or []
    except (ValueError, OSError, TypeError):
        return None
    missing = [e for e in episodes if isinstance(e, int) and not 0 <= e < total]
    if not missing:
        return None
    return (f"--dataset.episodes lists episode(s) {missing} that the dataset at --dataset.root={root} lacks (it has "
            f"{total}: 0..{total - 1}), so LeRobot looked for them on the Hub instead; list episodes it has")


def _hook(previous):
    def excepthook(kind: type[BaseException], error: BaseException, tb: TracebackType | None) -> None:
        quiet = os.environ.get(TRACEBACK_ENV) != "1"
        if quiet and isinstance(error, KeyboardInterrupt) and getattr(error, "said_by_pdp", False):
            prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
            print(f"{prog}: stopped: {error}", file=sys.stderr, flush=True)  # exit status still Ctrl-C's (130)
            return
        ours = pdp_message(error, tb) if quiet else None
        said = (layout_message(error) or dataset_message(sys.argv)) if quiet and ours is None else None
        if said is not None:
            prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
            print(f"{prog}: error: {said}", file=sys.stderr, flush=True)
            return
        if ours is None:
            previous(kind, error, tb)
            return
        message = str(ours.args[0] if isinstance(ours, KeyError) and ours.args else ours)
        prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
        message = message.removeprefix(f"{prog}: ")  # a message that names the command already
        print(f"{prog}: error: {message}\n({type(ours).__name__} from lerobot_pdp; {TRACEBACK_ENV}=1 shows the "
              "traceback)", file=sys.stderr, flush=True)

    excepthook.pdp_errors = True
    return excepthook


def install() -> None:
    """Put the hook in front of ``sys.excepthook`` in a LeRobot command (``lerobot-*`` but ``lerobot-pdp``, which
    prints its own errors so), once; a Python session or a user's script keeps Python's own."""
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    if not prog.startswith(("lerobot-", "lerobot_")) or prog == "lerobot-pdp":
        return
    if not getattr(sys.excepthook, "pdp_errors", False):
        sys.excepthook = _hook(sys.excepthook)


@contextlib.contextmanager
def ending_on_signals(prog: str) -> Iterator[None]:
    """SIGTERM (``systemctl stop``, ``docker stop``) unwinds the main thread as Ctrl-C does, through the program's
    ``finally`` blocks (a robot client stopped and its robot disconnected, a server shut down), where it killed the
    process on the spot; either ends the program with one line and the signal's exit status (130, 143), not a
    ``KeyboardInterrupt`` traceback. For LeRobot's robot client and policy server, which handle neither."""
    caught: list[int] = []

    def on_term(signum: int, frame: object) -> None:
        caught.append(signum)
        raise KeyboardInterrupt

    main = threading.current_thread() is threading.main_thread()
    before = signal.signal(signal.SIGTERM, on_term) if main else None
    try:
        yield
    except KeyboardInterrupt:
        signum = caught[0] if caught else int(signal.SIGINT)
        print(f"{prog}: stopped by {signal.Signals(signum).name}", file=sys.stderr, flush=True)
        raise SystemExit(128 + signum) from None
    finally:
        if before is not None:
            signal.signal(signal.SIGTERM, before)
