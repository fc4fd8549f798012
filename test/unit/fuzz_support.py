"""Shared strategies for the fuzz tests (test_fuzz_*.py): junk values and document mutation.

The fuzz tests take a VALID document (a camera_info, ring, map or scene mapping as YAML would give
it), apply one to three random mutations (replace a value by junk or by a "near miss" such as a
negative, zero, NaN or a string; delete a key; duplicate a list element; truncate a list) and
feed the result to the loader. The property is always the same: the loader either returns an
object or raises one of the package's own exceptions (:class:`errors.ArucoRingError`), and a
file error names its source.

Example counts: ``FUZZ_EXAMPLES`` (default 40, CI-sized) scales every fuzz test; ``make fuzz``
raises it (tools/fuzz.py).
"""
from __future__ import annotations

import copy
import math
import os
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

#: Examples per fuzz test (CI default; ``make fuzz`` sets FUZZ_EXAMPLES much higher).
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "40"))

#: Settings every fuzz test uses: the loaded profile (derandomized in CI) with our example count.
FUZZ = settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                              HealthCheck.filter_too_much])

scalars = (st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12)
           | st.sampled_from([0, -1, 1e308, -0.0, "0.2", "nan", "", [], {}]))

#: Anything YAML's safe_load can produce (minus dates), nested a little.
junk = st.recursive(scalars, lambda ch: st.lists(ch, max_size=5) | st.dictionaries(
    st.text(max_size=8) | st.integers(-3, 3), ch, max_size=5), max_leaves=12)


def near_misses(value: Any):
    """Values close to ``value`` that a careless hand edit produces."""
    out = [None, "", "x", [], {}, True]
    if isinstance(value, bool):
        out += [0, "yes"]
    elif isinstance(value, (int, float)):
        out += [-value, 0, -1, value * 1e9, float("nan"), float("inf"), -float("inf"), str(value),
                [value], float(value) + 0.5]
    elif isinstance(value, str):
        out += [value + "x", value[: len(value) // 2], 3, " " + value]
    elif isinstance(value, list):
        out += [value[:-1], value + value[-1:], value[:1], [str(v) for v in value], value * 3]
    elif isinstance(value, dict):
        out += [list(value.values()), {k: None for k in value}]
    return st.sampled_from(out)


def _mutate_once(data, node: Any) -> Any:
    """Return ``node`` with one random mutation somewhere inside it (``node`` is not modified)."""
    if isinstance(node, dict) and node:
        keys = sorted(node, key=str)
        k = data.draw(st.sampled_from(keys), label="key")
        action = data.draw(st.sampled_from(["descend", "descend", "replace", "near", "delete"]), label="action")
        node = dict(node)
        if action == "descend" and isinstance(node[k], (dict, list)) and node[k]:
            node[k] = _mutate_once(data, node[k])
        elif action == "delete":
            del node[k]
        elif action == "near":
            node[k] = data.draw(near_misses(node[k]), label="near")
        else:
            node[k] = data.draw(junk, label="junk")
        return node
    if isinstance(node, list) and node:
        i = data.draw(st.integers(0, len(node) - 1), label="index")
        action = data.draw(st.sampled_from(["descend", "descend", "replace", "near", "delete", "duplicate"]),
                           label="action")
        node = list(node)
        if action == "descend" and isinstance(node[i], (dict, list)) and node[i]:
            node[i] = _mutate_once(data, node[i])
        elif action == "delete":
            del node[i]
        elif action == "duplicate":
            node.insert(i, copy.deepcopy(node[i]))
        elif action == "near":
            node[i] = data.draw(near_misses(node[i]), label="near")
        else:
            node[i] = data.draw(junk, label="junk")
        return node
    return data.draw(near_misses(node) | junk, label="leaf")


def mutate(data, doc: Any, max_mutations: int = 3) -> Any:
    """Apply 1..max_mutations random mutations to a deep copy of ``doc``."""
    out = copy.deepcopy(doc)
    for _ in range(data.draw(st.integers(1, max_mutations), label="mutations")):
        out = _mutate_once(data, out)
    return out


def finite(x: float) -> bool:
    return isinstance(x, float) and math.isfinite(x)
