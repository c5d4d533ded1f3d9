"""Progress output: the one policy every ``fit``, dataset render, capture and sweep follows for
its bars and one-line messages (always on stderr, never on stdout).

A call's ``progress=`` argument decides when it is True or False. ``None``, every default, asks
the environment: ``JPRT_PROGRESS=0`` (or ``false``, ``no``, ``off``) silences all progress
output, any other value shows it, and when the variable is unset progress is shown when stderr
is a terminal, so logs, CI and tests stay clean while an interactive run shows its bars.

A leaf module (the standard library and tqdm only), so the solvers at the bottom of the package
use it too.
"""

from __future__ import annotations

import os
import sys
from typing import Callable, Iterable

__all__ = ["ENV", "enabled", "bar", "say"]

#: The environment variable that switches progress output on or off when a call does not say.
ENV = "JPRT_PROGRESS"

_OFF = ("0", "false", "no", "off")


def enabled(progress: bool | None = None) -> bool:
    """Whether to show progress: ``progress`` when it is a bool; else ``$JPRT_PROGRESS`` when it
    is set (off for 0 / false / no / off, on otherwise); else whether stderr is a terminal."""
    if progress is not None:
        return bool(progress)
    value = os.environ.get(ENV)
    if value is not None and value.strip():
        return value.strip().lower() not in _OFF
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # stderr replaced by an object without a terminal, or closed
        return False


def bar(iterable: Iterable | None = None, *, progress: bool | None = None, **kwargs):
    """A tqdm progress bar on stderr, shown when ``enabled(progress)``; ``kwargs`` go to tqdm
    (``total``, ``desc``, ``unit``, ``initial``, ``leave``...). Iterating it or calling
    ``update`` works the same whether it is shown or not."""
    from tqdm.auto import tqdm

    kwargs.setdefault("file", sys.stderr)
    return tqdm(iterable, disable=not enabled(progress), **kwargs)


def say(label: str, progress: bool | None = None) -> Callable[[str], None]:
    """A function printing one-line progress messages ``"label: message"`` on stderr when
    ``enabled(progress)`` (decided now, once), else doing nothing."""
    if not enabled(progress):
        return lambda message: None
    return lambda message: print(f"{label}: {message}", file=sys.stderr, flush=True)
