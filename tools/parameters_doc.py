#!/usr/bin/env python3
"""docs/parameters.md (and YAML skeletons) from the nodes' parameter schemas.

    python tools/parameters_doc.py            # rewrite docs/parameters.md
    python tools/parameters_doc.py --check    # exit 1 when docs/parameters.md is not current
    python tools/parameters_doc.py --yaml localizer   # a config/<node>.yaml skeleton on stdout

The schemas (:mod:`aruco_ring_localization.schemas`, the simulator's in ``ros/simulator.py``)
hold every parameter's name, default, unit and meaning, written once; the launch files hold their
arguments (``<arg>`` and the comment above it). ``test/unit/test_parameters_consistency.py`` uses
this module to check that the YAML files, the launch files, this document and the schemas agree.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import re
import sys
import textwrap
import xml.etree.ElementTree as ET
from typing import Any, Dict, Iterator, List, Optional, Tuple

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "src"))

from aruco_ring_localization import config as cfg  # noqa: E402
from aruco_ring_localization.schemas import NODE_SCHEMAS  # noqa: E402

DOC = os.path.join(REPO, "docs", "parameters.md")
LAUNCH_DIR = os.path.join(REPO, "launch")


def simulator_schema():
    """The simulator node's schema class (flat or nested), from ros/simulator.py."""
    from aruco_ring_localization.ros import simulator

    for name in ("SimulatorConfig", "SimulatorParams"):
        if hasattr(simulator, name):
            return getattr(simulator, name)
    raise ImportError("ros/simulator.py defines no SimulatorConfig or SimulatorParams")


def all_schemas() -> Dict[str, Tuple[Any, Optional[str]]]:
    """node -> (schema class, YAML file name or None), the simulator included."""
    out = dict(NODE_SCHEMAS)
    out["simulator"] = (simulator_schema(), "simulator.yaml")
    return out


# --- values -------------------------------------------------------------------------------------

def type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "double"
    if isinstance(value, (tuple, list)):
        return "list"
    if isinstance(value, dict):
        return "mapping"
    return "string"


def yaml_value(value: Any) -> str:
    """``value`` as a YAML scalar/flow sequence that reads back to the same Python value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return repr(value)
    if isinstance(value, float):
        text = repr(value)
        if "e" in text and "." not in text.split("e")[0]:
            text = text.replace("e", ".0e", 1)  # YAML 1.1 (PyYAML, rosparam) reads 1e-08 as a string
        return text
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {yaml_value(v)}" for k, v in value.items()) + "}"
    text = str(value)
    if text == "" or re.search(r"[:#\[\]{},&*!|>'\"%@`]|^\s|\s$", text) or text.lower() in (
            "true", "false", "yes", "no", "on", "off", "null", "~") or re.fullmatch(r"[-+.0-9eE]+", text):
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return text


def markdown_value(value: Any) -> str:
    return f"`{yaml_value(value)}`"


# --- launch files -------------------------------------------------------------------------------

#: The default of a launch argument that keeps the node's YAML value (the argument is passed on
#: only when given). Not an empty string: roslaunch's ros-args option lists those as "Required".
KEEP_YAML = "yaml"


def launch_args(path: str) -> List[Tuple[str, Optional[str], str]]:
    """``(name, default or None, doc)`` of every argument a launch file declares (its top-level
    ``<arg>``; those passed to an ``<include>`` are not its own)."""
    root = ET.parse(path).getroot()
    return [(el.get("name", ""), el.get("default", el.get("value")), " ".join((el.get("doc") or "").split()))
            for el in root if el.tag == "arg"]


def launch_files() -> List[str]:
    return sorted(os.path.join(LAUNCH_DIR, f) for f in os.listdir(LAUNCH_DIR) if f.endswith(".launch"))


def node_params(path: str) -> Iterator[Tuple[str, str, Dict[str, str]]]:
    """``(node type, parameter name, attributes)`` of every ``<param>`` / ``<rosparam param=>`` set on a node."""
    root = ET.parse(path).getroot()
    for node in root.iter("node"):
        typ = node.get("type", "")
        for p in node:
            if p.tag == "param":
                yield typ, p.get("name", ""), dict(p.attrib)
            elif p.tag == "rosparam" and p.get("param"):
                yield typ, p.get("param", ""), dict(p.attrib, value=(p.text or "").strip())


# --- the document -------------------------------------------------------------------------------

INTRO = """\
# Parameters of every node

<!-- Generated by tools/parameters_doc.py from the nodes' schemas and the launch files: do not
     edit by hand (a unit test checks that it is current). -->

Every node reads its private parameters (`~name`) once at start-up into its schema, a nested
frozen dataclass (`src/aruco_ring_localization/schemas.py`); each default is written once, in
that dataclass. Its YAML file in `config/` mirrors the schema key for key, with the same defaults
and the same prose, and the launch files load it with `<rosparam command="load">`. Nested keys are
sections: `estimator: {fusion: joint}` in the YAML is the parameter `~estimator/fusion`. A launch
argument overrides its key only when it is given (its default is empty: "use the YAML"), so no
launch file hides a YAML value. A key the schema does not know is warned about by name
(`unknown parameter 'gate.base_distanse' ignored`); a value of the wrong type, or one the schema
refuses, stops the node with an error naming the key. Units are SI (m, s, rad) unless the name
says `_deg` or `_px`, or the Unit column says otherwise.

The command-line tools read the same schemas from the same files: `aruco_ring localize` the
localizer's (`--config`, default `config/localization.yaml`), `aruco_ring build-map` the mapper's
(`--config`, default `config/mapping.yaml`); their options override single keys.
"""

NODE_TITLES = {
    "mapper": "`mapper` (`config/mapping.yaml`, `aruco_ring build-map`)",
    "localizer": "`localizer` (`config/localization.yaml`, `aruco_ring localize`)",
    "detector": "`detector` (`config/detector.yaml`)",
    "comparison": "`comparison` (`config/comparison.yaml`)",
    "ring_tf": "`ring_tf` (launch arguments)",
    "apriltag_relay": "`apriltag_relay` (launch arguments)",
    "simulator": "`simulator` (`config/simulator.yaml`)",
}

NODE_ORDER = ("mapper", "localizer", "detector", "ring_tf", "apriltag_relay", "comparison", "simulator")


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def node_table(schema) -> List[str]:
    lines = ["| Parameter | Type | Default | Unit | Meaning |", "|---|---|---|---|---|"]
    section_docs = dict(cfg.sections(schema))
    current = None
    for key, default, doc, unit in cfg.flatten(schema):
        section = key.rpartition(".")[0]
        if section != current and section:
            lines.append(f"| **{section.replace('.', '/')}**: {_cell(section_docs.get(section, ''))} | | | | |")
        current = section
        lines.append(f"| `~{key.replace('.', '/')}` | {type_name(default)} | {markdown_value(default)} | {unit} | "
                     f"{_cell(doc)} |")
    return lines


def render() -> str:
    schemas = all_schemas()
    out = [INTRO]
    out += ["## Launch files and their arguments", ""]
    out += [f"A default of `{KEEP_YAML}` means \"the node's YAML decides\" (the argument is passed on only when given). "
            "`roslaunch aruco_ring_localization FILE.launch --ros-args` prints the same list.", ""]
    for path in launch_files():
        out += [f"### `{os.path.basename(path)}`", "", "| Argument | Default | Meaning |", "|---|---|---|"]
        for name, d, comment in launch_args(path):
            out.append(f"| `{name}` | {'`' + d + '`' if d else '(empty)'} | {_cell(comment)} |")
        out.append("")
    for node in NODE_ORDER:
        schema, _ = schemas[node]
        out += [f"## {NODE_TITLES[node]}", ""]
        doc = (schema.__doc__ or "").strip().split("\n\n")[0]
        out += [" ".join(doc.split()), ""]
        out += node_table(schema)
        out.append("")
    out += ["## `make demo`", "",
            "The demo's options: `python -m aruco_ring_localization.ros.demo --help` (docs/evaluation.md).", ""]
    return "\n".join(out).rstrip() + "\n"


def yaml_skeleton(node: str) -> str:
    """A ``config/<node>.yaml`` body: every key with its default, its meaning as a comment."""
    schema, _ = all_schemas()[node]
    lines: List[str] = []

    def emit(cls, indent: str, base=None) -> None:
        for f in dataclasses.fields(cls):
            value = getattr(base, f.name) if base is not None else cfg._default_of(f)
            doc = " ".join(str(f.metadata.get("doc", "")).split())
            unit = f.metadata.get("unit", "")
            if cfg.is_section(f):
                lines.append("")
                lines.extend(textwrap.wrap(f"--- {f.name}: {doc}", 100, initial_indent=f"{indent}# ",
                                           subsequent_indent=f"{indent}#   "))
                lines.append(f"{indent}{f.name}:")
                emit(type(value), indent + "  ", value)
                continue
            if doc:
                text = f"{f.name}: {doc}{f' ({unit})' if unit else ''}."
                lines.extend(textwrap.wrap(text, 100, initial_indent=f"{indent}# ", subsequent_indent=f"{indent}#   "))
            lines.append(f"{indent}{f.name}: {yaml_value(value)}")
    emit(schema, "")
    return "\n".join(lines).lstrip("\n") + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when docs/parameters.md is not current")
    ap.add_argument("--yaml", metavar="NODE", help="print a config/<node>.yaml skeleton")
    args = ap.parse_args(argv)
    if args.yaml:
        sys.stdout.write(yaml_skeleton(args.yaml))
        return 0
    text = render()
    if args.check:
        current = open(DOC, encoding="utf-8").read() if os.path.exists(DOC) else ""
        if current != text:
            sys.stderr.write("docs/parameters.md is not current: run python tools/parameters_doc.py\n")
            return 1
        return 0
    with open(DOC, "w", encoding="utf-8") as fh:
        fh.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
