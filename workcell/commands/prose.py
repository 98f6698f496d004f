"""Wrapping prose for the terminal without breaking what a user copies out of it.

`textwrap` breaks lines at hyphens, so a long path could split ``--smr-offset`` into
``--smr-`` / ``offset``; a command or a path in a note must survive a copy and paste.
"""

from __future__ import annotations

import textwrap

__all__ = ["fill", "wrap"]


def wrap(text: str, width: int = 100, **kw) -> list[str]:
    """`textwrap.wrap` that breaks only at spaces (never inside an option, a path or a number)."""
    return textwrap.wrap(text, width=width, break_on_hyphens=False, break_long_words=False, **kw)


def fill(text: str, width: int = 100, **kw) -> str:
    """`textwrap.fill` that breaks only at spaces."""
    return "\n".join(wrap(text, width=width, **kw))
