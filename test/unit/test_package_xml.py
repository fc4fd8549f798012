"""package.xml matches the code: rosdep can install everything the package imports.

The imports of src/, scripts/ (the nodes), bench/, tools/, test/ and setup.py are read with ``ast``
(nothing is imported), every third-party top-level module is mapped to its rosdep key (the table
below), and package.xml must declare each key with the right dependency type:

* used by the package at run time (src/, scripts/, the launch files' ``<node pkg=...>``, the
  commands the user docs tell a ROS user to run): ``exec_depend`` (or ``depend``);
* used only by tests, benchmarks and tools (and the rostest files' ``<node pkg=...>``): ``test_depend``;
* used by setup.py (the build): ``build_depend`` or ``buildtool_depend``.

It fails on an import that is not in the table, on a key that is not declared or declared with the
wrong type, and on a declared key that nothing uses. Python packages that Debian/Ubuntu do not ship
are declared with rosdep's pip keys (``python3-<name>-pip``, rosdistro's python.yaml convention);
keys that rosdistro does not define are defined in rosdep/aruco_ring.yaml (docs/install.md says how
to add it to rosdep's sources), and each pip key's package is pinned in requirements.txt.
"""
from __future__ import annotations

import ast
import re
import sys
import sysconfig
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict, Iterable, Iterator, Set, Tuple

import pytest
import yaml

from helpers import REPO

# Top-level import -> rosdep key. ROS packages by their package name; Python libraries by their
# rosdep key (rosdistro's rosdep/python.yaml; "-pip" keys install from PyPI).
IMPORT_TO_KEY: Dict[str, str] = {
    # ROS
    "rospy": "rospy",
    "rosbag": "rosbag",
    "rosgraph": "rosgraph",
    "rosgraph_msgs": "rosgraph_msgs",
    "rospkg": "python3-rospkg",
    "genpy": "genpy",
    "rostest": "rostest",
    "tf2_ros": "tf2_ros",
    "tf2_py": "tf2_py",
    "tf2_msgs": "tf2_msgs",
    "diagnostic_msgs": "diagnostic_msgs",
    "diagnostic_updater": "diagnostic_updater",
    "geometry_msgs": "geometry_msgs",
    "nav_msgs": "nav_msgs",
    "sensor_msgs": "sensor_msgs",
    "std_msgs": "std_msgs",
    "std_srvs": "std_srvs",
    "visualization_msgs": "visualization_msgs",
    "fiducial_msgs": "fiducial_msgs",
    "rviz": "rviz",
    "python_qt_binding": "python_qt_binding",
    # Python libraries from Debian/Ubuntu packages
    "numpy": "python3-numpy",
    "cv2": "python3-opencv",
    "scipy": "python3-scipy",
    "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
    # Python libraries from PyPI (rosdep pip keys)
    "filterpy": "python3-filterpy-pip",
    "evo": "python3-evo-pip",
    "threadpoolctl": "python3-threadpoolctl-pip",
    # the build (setup.py)
    "setuptools": "python3-setuptools",
    "catkin_pkg": "catkin",
}

# pip keys that rosdistro's rosdep/python.yaml defines (checked there; the others are ours).
UPSTREAM_PIP_KEYS = {"python3-filterpy-pip"}

# Keys used by what the user docs tell a ROS user to type, not by an import: key -> the command.
COMMAND_KEYS: Dict[str, str] = {
    "rosbash": "rosrun aruco_ring_localization",
    "tf": "rosrun tf tf_echo",
}

# Packages that only an example launch file starts, not declared (so that rosdep works where they
# are not packaged): package -> the launch file, whose header says how to install it.
OPTIONAL_LAUNCH_PACKAGES: Dict[str, str] = {
    "robot_localization": "robot_localization_example.launch",  # not in Debian 12
}

# Launch files are run by roslaunch (the package's runtime).
LAUNCH_KEY = "roslaunch"

RUNTIME_DIRS = ("src", "scripts")
TEST_DIRS = ("test", "bench", "tools")
USER_DOCS = ["README.md"] + [str(p.relative_to(REPO)) for p in sorted((REPO / "docs").glob("*.md"))]

EXEC_TYPES = {"exec_depend", "depend", "run_depend"}
TEST_TYPES = {"test_depend"}
BUILD_TYPES = {"build_depend", "buildtool_depend", "depend", "build_export_depend"}


def python_files(root: Path) -> Iterator[Path]:
    """The .py files under root and its extensionless Python scripts (shebang naming python)."""
    for path in sorted(root.rglob("*")):
        if not path.is_file() or ".venv" in path.parts or ".ws" in path.parts:
            continue
        if path.suffix == ".py":
            yield path
        elif path.suffix == "" and path.read_bytes()[:80].startswith(b"#!") and b"python" in path.read_bytes()[:80]:
            yield path


def top_level_imports(path: Path) -> Set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def stdlib_names() -> Set[str]:
    names = set(getattr(sys, "stdlib_module_names", ())) | set(sys.builtin_module_names)
    if not getattr(sys, "stdlib_module_names", None):  # Python < 3.10 (Noetic's 3.8)
        stdlib = Path(sysconfig.get_paths()["stdlib"])
        for p in stdlib.iterdir():
            if p.name in ("site-packages", "dist-packages"):
                continue
            names.add(p.name[:-3] if p.suffix == ".py" else p.name.split(".")[0])
        dynload = stdlib / "lib-dynload"
        if dynload.is_dir():
            names.update(p.name.split(".")[0] for p in dynload.iterdir())
    names.add("__future__")
    return names


def local_modules() -> Set[str]:
    """First-party names: the package itself and the test/bench helper modules imported by name."""
    names = {"aruco_ring_localization"}
    for d in TEST_DIRS:
        names.update(p.stem for p in (REPO / d).rglob("*.py"))
    return names


def third_party_imports(dirs: Iterable[str]) -> Dict[str, Set[str]]:
    """module -> the files (relative) that import it, for the third-party modules of dirs."""
    skip = stdlib_names() | local_modules()
    found: Dict[str, Set[str]] = {}
    for d in dirs:
        root = REPO / d
        files = [root] if root.is_file() else python_files(root)
        for path in files:
            for name in top_level_imports(path) - skip:
                found.setdefault(name, set()).add(str(path.relative_to(REPO)))
    return found


def declared() -> Dict[str, Set[str]]:
    """key -> the dependency types under which package.xml declares it."""
    root = ET.parse(str(REPO / "package.xml")).getroot()
    deps: Dict[str, Set[str]] = {}
    for el in root:
        if el.tag.endswith("depend"):
            deps.setdefault(el.text.strip(), set()).add(el.tag)
    return deps


def launch_packages(pattern: str = "launch/*.launch") -> Set[str]:
    """The packages of the ``<node>``s of the launch (or rostest) files matching pattern."""
    pkgs = set()
    for path in sorted(REPO.glob(pattern)):
        for node in ET.parse(str(path)).getroot().iter("node"):
            if OPTIONAL_LAUNCH_PACKAGES.get(node.get("pkg")) != path.name:
                pkgs.add(node.get("pkg"))
    return pkgs - {"aruco_ring_localization"}


def docs_text() -> str:
    return "\n".join((REPO / f).read_text() for f in USER_DOCS)


def keys_for(imports: Dict[str, Set[str]]) -> Dict[str, Set[str]]:
    unknown = {m: sorted(f)[:3] for m, f in imports.items() if m not in IMPORT_TO_KEY}
    assert not unknown, (f"third-party imports without a rosdep key in {Path(__file__).name}'s IMPORT_TO_KEY "
                         f"(add the key there and to package.xml): {unknown}")
    keys: Dict[str, Set[str]] = {}
    for m, files in imports.items():
        keys.setdefault(IMPORT_TO_KEY[m], set()).update(files)
    return keys


def usage() -> Tuple[Dict[str, Set[str]], Dict[str, Set[str]], Dict[str, Set[str]]]:
    """(runtime, test-only, build) key -> what uses it."""
    runtime = keys_for(third_party_imports(RUNTIME_DIRS))
    for pkg in launch_packages():
        runtime.setdefault(pkg, set()).add("launch/ <node pkg=...>")
    runtime.setdefault(LAUNCH_KEY, set()).add("launch/*.launch")
    text = docs_text()
    for key, command in COMMAND_KEYS.items():
        if command in text:
            runtime.setdefault(key, set()).add(f"docs: {command}")
    tests = keys_for(third_party_imports(TEST_DIRS))
    for pkg in launch_packages("test/integration/*.test"):
        tests.setdefault(pkg, set()).add("test/integration/*.test <node pkg=...>")
    tests = {k: v for k, v in tests.items() if k not in runtime}
    build = keys_for(third_party_imports(["setup.py"]))
    return runtime, tests, build


def test_every_runtime_import_is_an_exec_depend():
    runtime, _, _ = usage()
    deps = declared()
    wrong = {k: sorted(v)[:2] for k, v in runtime.items() if not deps.get(k, set()) & EXEC_TYPES}
    assert not wrong, f"package.xml: used at run time but not an exec_depend: {wrong}"


def test_every_test_only_import_is_a_test_depend():
    _, tests, _ = usage()
    deps = declared()
    missing = {k: sorted(v)[:2] for k, v in tests.items() if not deps.get(k, set()) & TEST_TYPES}
    assert not missing, f"package.xml: used only by tests/bench/tools but not a test_depend: {missing}"
    as_exec = sorted(k for k in tests if deps.get(k, set()) & EXEC_TYPES)
    assert not as_exec, f"package.xml: test-only dependencies declared as exec_depend: {as_exec}"


def test_the_build_imports_are_build_dependencies():
    _, _, build = usage()
    deps = declared()
    missing = sorted(k for k in build if not deps.get(k, set()) & BUILD_TYPES)
    assert not missing, f"package.xml: setup.py needs {missing} as build_depend/buildtool_depend"


def test_no_declared_dependency_is_unused():
    runtime, tests, build = usage()
    deps = declared()
    unused = sorted(k for k in deps if k not in runtime and k not in tests and k not in build)
    assert not unused, f"package.xml declares dependencies nothing uses: {unused}"
    runtime_as_test = sorted(k for k in runtime if deps.get(k, set()) & TEST_TYPES)
    assert not runtime_as_test, f"package.xml: run-time dependencies also (redundantly) test_depend: {runtime_as_test}"


def test_pip_keys_are_defined_and_pinned():
    """A pip key rosdistro lacks is defined in rosdep/aruco_ring.yaml (pip, the PyPI name), and
    every pip key's package is pinned in requirements.txt (what tools/setup.sh installs)."""
    ours = yaml.safe_load((REPO / "rosdep" / "aruco_ring.yaml").read_text())
    pins = {re.split(r"[=<>!~ ]", line, 1)[0].strip().lower()
            for line in (REPO / "requirements.txt").read_text().splitlines() if line.strip() and not line.startswith("#")}
    pip_keys = sorted(k for k in declared() if k.endswith("-pip"))
    assert pip_keys, "no pip key declared (filterpy and evo come from PyPI)"
    for key in pip_keys:
        if key in UPSTREAM_PIP_KEYS:
            pypi = key[len("python3-"):-len("-pip")]
            assert key not in ours, f"rosdep/aruco_ring.yaml redefines rosdistro's {key}"
        else:
            assert key in ours, f"{key} is not in rosdistro: define it in rosdep/aruco_ring.yaml"
            for os_name in ("debian", "ubuntu"):
                assert ours[key][os_name]["pip"]["packages"], f"rosdep/aruco_ring.yaml: {key}: no {os_name} pip package"
            (pypi,) = ours[key]["ubuntu"]["pip"]["packages"]
        assert pypi.lower() in pins, f"{key}: {pypi} is not pinned in requirements.txt"
    stray = sorted(set(ours) - set(pip_keys))
    assert not stray, f"rosdep/aruco_ring.yaml defines keys package.xml does not use: {stray}"


@pytest.mark.parametrize("source, key", [
    ("import filterpy.kalman\n", "python3-filterpy-pip"),
    ("from cv2 import aruco\n", "python3-opencv"),
    ("import rosgraph_msgs.msg\n", "rosgraph_msgs"),
])
def test_the_import_scan_sees_imports(tmp_path, source, key):
    """The scan itself: a file's import is found and mapped (so an undeclared one cannot hide)."""
    f = tmp_path / "m.py"
    f.write_text("from __future__ import annotations\nimport os\n" + source)
    names = top_level_imports(f) - stdlib_names()
    assert [IMPORT_TO_KEY[n] for n in names] == [key]
