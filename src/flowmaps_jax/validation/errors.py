"""One place that says where an error happened: :func:`prefix_errors` puts the file (or the
command) in front of every check's message inside its block."""

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
