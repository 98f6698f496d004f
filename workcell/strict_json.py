"""JSON files written by hand (envelopes, bounds): a key given twice is refused, not silently
replaced by its last value as `json.loads` does."""

from __future__ import annotations

import json
from typing import Any


class DuplicateKey(ValueError):
    """A JSON object gives the key `args[0]` twice."""


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    seen: dict = {}
    for k, v in pairs:
        if k in seen:
            raise DuplicateKey(k)
        seen[k] = v
    return seen


def loads(text: str) -> Any:
    """`json.loads`, raising `DuplicateKey` for a key given twice in any object."""
    return json.loads(text, object_pairs_hook=_no_duplicates)
