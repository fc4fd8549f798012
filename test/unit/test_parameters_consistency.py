"""One parameter schema per node: config/*.yaml, every launch file, docs/parameters.md and the
dataclasses agree in name and default.

* each node's YAML mirrors its schema key for key, with the schema's defaults (the simulator's,
  flat or nested, is checked for its keys and defaults: its launch file sets the others);
* every ``<param>`` a launch file sets on one of our nodes names a key of that node's schema; a
  value from ``$(arg X)`` comes from an argument named like the key's last part, whose default is
  ``yaml`` and which is only passed on when given (``if="$(eval arg('X') != 'yaml')"``) unless the
  YAML holds nothing to hide there (an empty string); a literal value is a mode switch (``if``/``unless``);
  an argument's literal default, where it has one, is the schema's;
* every launch argument has a ``doc=`` and a non-empty default (roslaunch lists an empty one as
  "Required");
* docs/parameters.md is what tools/parameters_doc.py generates, and every field documents itself.
"""
from __future__ import annotations

import importlib.util
import os
import xml.etree.ElementTree as ET

import pytest
import yaml

from aruco_ring_localization.config import coerce, flatten

from helpers import REPO

_spec = importlib.util.spec_from_file_location("parameters_doc", REPO / "tools" / "parameters_doc.py")
doc_tool = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(doc_tool)

SCHEMAS = doc_tool.all_schemas()
#: launch file node ``type`` -> schema node name.
NODE_TYPES = {"localizer": "localizer", "mapper": "mapper", "detector": "detector", "ring_tf": "ring_tf",
              "comparison": "comparison", "simulator": "simulator", "apriltag_relay": "apriltag_relay"}
OURS = {"localizer", "mapper", "detector", "ring_tf", "comparison", "apriltag_relay"}


def _flat_yaml(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flat_yaml(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def _defaults(node):
    return {k: d for k, d, _, _ in flatten(SCHEMAS[node][0])}


def _yaml(node):
    name = SCHEMAS[node][1]
    return dict(_flat_yaml(yaml.safe_load((REPO / "config" / name).read_text()) or {})) if name else {}


@pytest.mark.parametrize("node", sorted(n for n, (_, f) in SCHEMAS.items() if f))
def test_yaml_mirrors_the_schema(node):
    defaults, values = _defaults(node), _yaml(node)
    unknown = sorted(set(values) - set(defaults))
    assert not unknown, f"config/{SCHEMAS[node][1]}: keys the schema does not know: {unknown}"
    if node in OURS:
        missing = sorted(set(defaults) - set(values))
        assert not missing, f"config/{SCHEMAS[node][1]}: schema keys missing from the YAML: {missing}"
    wrong = {k: (v, defaults[k]) for k, v in values.items() if coerce(k, v, defaults[k], "yaml") != defaults[k]}
    assert not wrong, f"config/{SCHEMAS[node][1]}: value != schema default: {wrong}"


def _launch_params():
    """(launch file, node type, param element, {arg: default})."""
    for path in sorted((REPO / "launch").glob("*.launch")):
        args = {name: d for name, d, _ in doc_tool.launch_args(str(path))}
        root = ET.parse(path).getroot()
        for node in root.iter("node"):
            typ = node.get("type", "")
            if typ not in NODE_TYPES:
                continue
            for p in node:
                if p.tag == "param" or (p.tag == "rosparam" and p.get("param")):
                    yield path.name, NODE_TYPES[typ], p, args


PARAMS = list(_launch_params())


def test_launch_files_set_parameters_of_our_nodes():
    nodes = {node for _, node, _, _ in PARAMS}
    assert {"localizer", "mapper", "detector", "ring_tf", "comparison", "simulator", "apriltag_relay"} <= nodes, nodes


@pytest.mark.parametrize("launch, node, el, args", PARAMS,
                         ids=[f"{f}:{n}:{e.get('name') or e.get('param')}" for f, n, e, _ in PARAMS])
def test_launch_params_name_schema_keys_and_never_hide_the_yaml(launch, node, el, args):
    key = (el.get("name") or el.get("param")).replace("/", ".")
    defaults = _defaults(node)
    assert key in defaults, f"{launch}: <param {key}> is not a parameter of {node} (docs/parameters.md)"
    value = el.get("value") if el.tag == "param" else (el.text or "").strip()
    cond = el.get("if", "") + el.get("unless", "")
    yaml_value = _yaml(node).get(key)
    if value.startswith("$(arg ") and value.endswith(")"):
        arg = value[len("$(arg "):-1]
        assert arg in args, f"{launch}: {key} from undeclared arg {arg}"
        default = args[arg]
        # A default that the condition tests against (yaml, none) means "not given", not a value.
        if default and "$(" not in default and f"arg('{arg}') != '{default}'" not in cond:
            assert coerce(key, yaml.safe_load(default), defaults[key], launch) == defaults[key], \
                f"{launch}: arg {arg} defaults to {default!r}, the schema's {key} to {defaults[key]!r}"
        if node in OURS:
            assert arg == key.rpartition(".")[2], f"{launch}: arg {arg} sets {key}: one name per thing"
        hides = yaml_value is not None and yaml_value != ""
        keep = f"arg('{arg}') != '{doc_tool.KEEP_YAML}'"
        if hides and node in OURS:
            assert default == doc_tool.KEEP_YAML and keep in cond, \
                f"{launch}: <param {key}> from arg {arg} (default {default!r}) would hide the YAML's {yaml_value!r}"
        elif hides:
            assert default == doc_tool.KEEP_YAML or keep in cond, \
                f"{launch}: <param {key}> from arg {arg} (default {default!r}) hides the YAML's {yaml_value!r}"
    elif node in OURS:
        assert cond, f"{launch}: <param {key} value={value!r}> always set: a launch file must not fix a YAML value"


def test_every_launch_argument_is_documented_and_none_looks_required():
    """roslaunch's ros-args option prints each argument's doc (\"undocumented\" without one) and lists an
    argument whose default is empty as \"Required\": none of ours is."""
    for path in doc_tool.launch_files():
        for name, default, doc in doc_tool.launch_args(path):
            where = f"{os.path.basename(path)}: arg {name}"
            assert doc, f"{where} has no doc= attribute"
            assert default, f"{where} has an empty default: roslaunch would list it as Required"


def test_parameters_doc_is_current():
    current = (REPO / "docs" / "parameters.md").read_text()
    assert current == doc_tool.render(), "docs/parameters.md is not current: run python tools/parameters_doc.py"


@pytest.mark.parametrize("node", sorted(OURS))
def test_every_parameter_documents_itself(node):
    undocumented = [k for k, _, d, _ in flatten(SCHEMAS[node][0]) if not d.strip()]
    assert not undocumented, f"{node}: parameters without a doc: {undocumented}"


def test_yaml_skeletons_read_back_as_the_defaults():
    for node in OURS:
        text = doc_tool.yaml_skeleton(node)
        values = dict(_flat_yaml(yaml.safe_load(text) or {}))
        assert values == {k: (list(v) if isinstance(v, tuple) else v) for k, v in _defaults(node).items()}, node


def test_one_name_per_thing():
    keys = {node: {k.rpartition(".")[2] for k in _defaults(node)} for node in OURS}
    assert "pixel_sigma" not in keys["mapper"] and "pixel_noise" in keys["mapper"] and "pixel_noise" in keys["localizer"]
    assert _defaults("mapper")["input.camera_info_fallback"] is False
    assert _defaults("localizer")["input.camera_info_fallback"] is False
    assert _defaults("detector")["fiducial_len"] == _defaults("mapper")["markers.fiducial_len"] == 0.20


def test_detect_command_defaults_are_the_detector_nodes():
    from aruco_ring_localization.cli import build_parser

    args = build_parser().parse_args(["detect", "x.png", "--camera-info", "c.yaml"])
    d = _defaults("detector")
    assert (args.fiducial_len, args.dictionary, args.corner_refinement) == \
        (d["fiducial_len"], d["dictionary"], d["corner_refinement"])
