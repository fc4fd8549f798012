"""config/diagnostics_aggregator.yaml sorts every status the localizer publishes into exactly one
analyzer, by diagnostic_aggregator's GenericAnalyzer matching rules (``name``, ``expected``,
``startswith``, ``contains``, ``regex``, ``find_and_remove_prefix``, ``remove_prefix`` does not
match). The names are diagnostic_updater's ``<node>: <task>`` (localizer.test checks the node's)."""
from __future__ import annotations

import re
from typing import Dict, List

import yaml

from aruco_ring_localization.ring import CameraRing
from helpers import REPO

CONFIG = REPO / "config" / "diagnostics_aggregator.yaml"
MATCH_KEYS = ("name", "expected", "startswith", "contains", "regex", "find_and_remove_prefix")
TYPES = {"diagnostic_aggregator/GenericAnalyzer", "diagnostic_aggregator/AnalyzerGroup"}


def published_names() -> List[str]:
    ring = CameraRing.load(str(REPO / "config" / "ring.yaml"))
    return [f"localizer: camera {c.name}" for c in ring.cameras] + ["localizer: filter"]


def _as_list(v) -> List[str]:
    return [v] if isinstance(v, str) else list(v or [])


def generic_analyzers(node: Dict, path: str = "") -> Dict[str, Dict]:
    """'/Group/Path' -> the GenericAnalyzer's parameters, through AnalyzerGroups."""
    out = {}
    for key, a in node.items():
        assert a.get("type") in TYPES, f"{CONFIG.name}: {key}: type {a.get('type')!r}"
        assert a.get("path"), f"{CONFIG.name}: {key}: no path"
        here = f"{path}/{a['path']}"
        if a["type"].endswith("AnalyzerGroup"):
            out.update(generic_analyzers(a["analyzers"], here))
        else:
            assert any(k in a for k in MATCH_KEYS), f"{CONFIG.name}: {key} matches nothing"
            out[here] = a
    return out


def matches(a: Dict, name: str) -> bool:
    return (name in _as_list(a.get("name")) or name in _as_list(a.get("expected"))
            or any(name.startswith(p) for p in _as_list(a.get("startswith")) + _as_list(a.get("find_and_remove_prefix")))
            or any(c in name for c in _as_list(a.get("contains")))
            or any(re.match(r, name) for r in _as_list(a.get("regex"))))


def test_every_localizer_status_has_exactly_one_analyzer():
    analyzers = generic_analyzers(yaml.safe_load(CONFIG.read_text())["analyzers"])
    for name in published_names():
        hits = [p for p, a in analyzers.items() if matches(a, name)]
        assert len(hits) == 1, f"{CONFIG.name}: status {name!r} is matched by {hits or 'no analyzer'}"
    assert {p for p, a in analyzers.items() if any(matches(a, n) for n in published_names())} == set(analyzers), \
        "an analyzer matches none of the localizer's statuses"


def test_expected_statuses_are_published_ones():
    analyzers = generic_analyzers(yaml.safe_load(CONFIG.read_text())["analyzers"])
    for path, a in analyzers.items():
        for name in _as_list(a.get("expected")):
            assert name in published_names(), f"{CONFIG.name}: {path} expects {name!r}, which nobody publishes"


def test_matching_rules_themselves():
    a = {"find_and_remove_prefix": ["localizer: camera "]}
    assert matches(a, "localizer: camera cam3") and not matches(a, "localizer: filter")
    assert matches({"expected": ["x: y"]}, "x: y") and not matches({"contains": ["zz"]}, "x: y")
