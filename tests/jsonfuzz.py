"""Hypothesis helpers shared by the bad-input tests: any JSON value put into any field."""

from __future__ import annotations

from hypothesis import strategies as st

JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**6)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=7) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
    ),
    max_leaves=8,
)


def field_paths(obj, prefix=()):
    """Every key path of nested dicts: ('tool',), ('tool', 'smr_offset_m'), ..."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield (*prefix, k)
            yield from field_paths(v, (*prefix, k))


def replace_any_field(data, obj: dict) -> tuple[tuple, object]:
    """Draw a field of `obj` and a JSON value; put the value there (in place)."""
    path = data.draw(st.sampled_from(sorted(field_paths(obj), key=str)), label="field")
    value = data.draw(JSON, label="value")
    o = obj
    for k in path[:-1]:
        o = o[k]
    o[path[-1]] = value
    return path, value
