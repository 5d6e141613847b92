"""Config errors that reach the user through LeRobot's command-line parser.

draccus (LeRobot's command-line and config-file parser) turns a ValueError raised while it builds a dataclass
into "Couldn't instantiate class ... using the given arguments", dropping the message that names the field; a
``DecodingError`` passes through it to LeRobot's parser, which prints it. PDP's policy, robot and teleoperator
configs raise :func:`config_error` from ``__post_init__``: a Python caller still gets a ValueError.
"""

from __future__ import annotations

import sys


def config_error(message: str) -> Exception:
    """The exception a config's ``__post_init__`` raises for ``message`` (see the module)."""
    if _decoded_by_draccus():
        from draccus.utils import DecodingError

        return DecodingError((), message)
    return ValueError(message)


def _decoded_by_draccus() -> bool:
    """True when the config being built is built by draccus: its ``decode_dataclass`` is a few frames up."""
    frame = sys._getframe(1)
    for _ in range(8):
        if frame is None:
            return False
        if frame.f_code.co_name == "decode_dataclass" and frame.f_globals.get("__name__", "").startswith("draccus"):
            return True
        frame = frame.f_back
    return False
