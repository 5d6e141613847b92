"""A clean console: LeRobot's torchcodec fallback warning in one line when FFmpeg is simply not installed, and
latents printed at a readable precision (:func:`latent_text`), a run's losses summarised (:func:`loss_ends_text`).

LeRobot picks its default video decoder in ``lerobot.utils.import_utils.get_safe_default_video_backend``: it
imports torchcodec and, when that fails, logs ``f"{e}\\n'torchcodec' is installed but cannot be loaded ..."``
at WARNING and falls back to 'pyav'. torchcodec's error ``e`` embeds one Python traceback per FFmpeg major
version it tried (8 to 4), so on a machine without FFmpeg's shared libraries (most fresh machines) every
``lerobot-train``, ``lerobot-eval`` and ``lerobot-pdp`` command prints ~100 lines of tracebacks, and again each
time LeRobot asks (each ``DatasetConfig`` and each ``LeRobotDataset`` built without a ``video_backend``).

``install()`` puts a filter on that one LeRobot logger. It rewrites the record to one line only when *every*
FFmpeg version torchcodec tried failed because an FFmpeg shared library (libavutil, libavcodec, ...) is not
found, and reports it once per process. Any other failure (FFmpeg present but an incompatible PyTorch, a missing
symbol, an unknown format of the message) is left as LeRobot logs it, in full; no other record is touched.
Decoding errors (a corrupt video) are raised by the decoders and never pass through this logger.
"""

from __future__ import annotations

import logging
import re
from typing import Any

LOGGER_NAME = "lerobot.utils.import_utils"
MARKER = "'torchcodec' is installed but cannot be loaded"
ONE_LINE = (
    "torchcodec cannot be loaded: FFmpeg's shared libraries are not installed ({missing} not found); "
    "falling back to 'pyav' as a default decoder (install FFmpeg 4-8 to decode with torchcodec)."
)

_VERSION_BLOCK = re.compile(r"^FFmpeg version (\d+):\n(.*?)(?=^FFmpeg version \d+:|\[end of libtorchcodec)",
                            re.MULTILINE | re.DOTALL)
_FFMPEG_LIB = r"lib(?:av(?:util|codec|format|device|filter)|sw(?:scale|resample)|postproc)"
# Linux: "OSError: libavutil.so.60: cannot open shared object file"; macOS: "Library not loaded: @rpath/libavutil.60.dylib"
_MISSING_LIB = re.compile(rf"({_FFMPEG_LIB}\.so\.\d+): cannot open shared object file|"
                          rf"Library not loaded: \S*?({_FFMPEG_LIB}\.\d+\.dylib)")


def missing_ffmpeg_libraries(message: str) -> list[str] | None:
    """The FFmpeg libraries torchcodec did not find, if that is the only reason every version failed, else None."""
    blocks = _VERSION_BLOCK.findall(message)
    if not blocks:
        return None
    missing: list[str] = []
    for _version, block in blocks:
        found = [a or b for a, b in _MISSING_LIB.findall(block)]
        if not found:  # this version failed for another reason: a real error, shown in full
            return None
        missing += [lib for lib in found if lib not in missing]
    return missing


class TorchcodecFallbackFilter(logging.Filter):
    """Condenses LeRobot's "torchcodec cannot be loaded" warning to one line, once, when FFmpeg is absent."""

    def __init__(self) -> None:
        super().__init__()
        self.reported = False

    def filter(self, record: logging.LogRecord) -> bool:
        if not isinstance(record.msg, str) or MARKER not in record.msg:
            return True
        missing = missing_ffmpeg_libraries(record.getMessage())
        if missing is None:
            return True
        if self.reported:
            return False
        self.reported = True
        record.msg, record.args = ONE_LINE.format(missing=", ".join(missing)), ()
        record.exc_info = record.exc_text = None
        return True


def install() -> None:
    """Put the filter on LeRobot's import_utils logger (once; the logger need not exist yet)."""
    logger = logging.getLogger(LOGGER_NAME)
    if not any(isinstance(f, TorchcodecFallbackFilter) for f in logger.filters):
        logger.addFilter(TorchcodecFallbackFilter())


def counted(n: int, noun: str) -> str:
    """``"1 demonstration"``, ``"3 demonstrations"``: a count and its noun, singular for one."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def latent_text(z: Any, digits: int = 4) -> str:
    """A latent (tensor, array or nested list) as the console shows it: each value rounded to ``digits`` decimals,
    the nesting kept (``[[1.3871, -0.8325]]`` for one phase latent); anything else (None: the default latent) as it
    is. Files keep full precision; this is for reading."""
    def rounded(v: Any) -> Any:
        if isinstance(v, (list, tuple)):
            return [rounded(x) for x in v]
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            return v
        v = float(v)  # a huge value (a typo'd exponent) to ``digits`` significant digits: 1e+30, not 1.00000001e+30
        return float(f"{v:.{digits}g}") if abs(v) >= 1e6 else round(v, digits)

    return str(rounded(z.tolist() if hasattr(z, "tolist") else z))


def loss_ends_text(losses: list[float], window: int = 10) -> str:
    """The mean loss over the first and over the last ``window`` steps (half of a shorter run), for a result's
    summary: one step's loss against another's is mostly their batches' noise."""
    if not losses:
        return "none"
    n = max(1, min(window, len(losses) // 2))
    first, last = sum(losses[:n]) / n, sum(losses[-n:]) / n
    return f"{first:.4g} -> {last:.4g}" + (f" (means of the first and last {n} steps)" if n > 1 else "")
