"""JSON files written or edited by hand (envelopes, bounds, models, tables): a key given twice is
refused, not silently replaced by its last value as `json.loads` does."""

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


def _int(s: str) -> int | float:
    """A JSON integer; one beyond 64 bits as a float (inf past 1e308), as a JSON number with a
    decimal point or exponent is read: `float(10**400)` raised OverflowError deep in a loader
    (a traceback), while the loaders' finiteness checks name an inf."""
    if len(s) > 40:  # beyond 64 bits anyway; int() refuses over 4300 digits with a hint at
        return float(s)  # sys.set_int_max_str_digits, meaningless to the file's author
    v = int(s)
    return v if -(2**63) <= v < 2**63 else float(s)


def loads(text: str) -> Any:
    """`json.loads` for files written or edited by hand (envelopes, bounds, models, tables):
    a key given twice in any object is a `DuplicateKey` (a model with "theta" twice was read
    with the later one, 4 mm off, until 2026-11-29), integers beyond 64 bits are floats
    (`_int`), and nesting deeper than Python's parser recurses is a `json.JSONDecodeError`
    (not a RecursionError past the loaders' checks)."""
    return _loads(text, object_pairs_hook=_no_duplicates)


def _loads(text: str, **kw) -> Any:
    """`json.loads` with `_int`; nesting deeper than the parser recurses (a RecursionError) is
    a `json.JSONDecodeError`, what the loaders catch."""
    try:
        return json.loads(text, parse_int=_int, **kw)
    except RecursionError:
        doc = text if isinstance(text, str) else ""
        raise json.JSONDecodeError("nested too deeply to read", doc, 0) from None


def finite(v: Any) -> Any:
    """JSON-ready copy of `v`: numpy arrays and scalars as lists and numbers, paths as strings,
    a non-finite float (NaN, inf) as None (JSON has neither)."""
    import math
    import os

    if isinstance(v, os.PathLike):
        return os.fspath(v)
    if hasattr(v, "tolist"):  # numpy array or scalar
        v = v.tolist()
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, list | tuple):
        return [finite(x) for x in v]
    if isinstance(v, dict):
        return {k: finite(x) for k, x in v.items()}
    return v


def dumps(v: Any, **kw) -> str:
    """Strict JSON of a command's result: `finite(v)`, written with allow_nan=False (Python's
    default writes NaN and Infinity, which JSON readers refuse)."""
    return json.dumps(finite(v), allow_nan=False, **kw)
