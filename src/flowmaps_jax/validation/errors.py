"""One place that says where an error happened: :func:`prefix_errors`.

A loader checks many things about one file, each with a check that names only the part it
reads (``format_version``, ``scenes.slot``); wrapping them all in ``with prefix_errors(...)``
puts the file (or the command) in front of every such message once, instead of one
``try``/``except``/``raise`` around each check.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


@contextlib.contextmanager
def prefix_errors(prefix: str, *, also: tuple[type[BaseException], ...] = ()) -> Iterator[None]:
    """Re-raise a ``ValueError`` (or one of ``also``, e.g. ``TypeError`` from a constructor fed
    an untrusted dict) raised inside the block as a ``ValueError`` whose message is ``prefix``
    followed by the original message."""
    try:
        yield
    except (ValueError, *also) as err:
        raise ValueError(f"{prefix}{err}") from err
