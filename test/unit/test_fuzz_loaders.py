"""Fuzzing of every file loader and text parser of the core (issue 7, "fuzzing").

Property: for any input, a loader returns a valid object or raises one of the package's own
exceptions (``ArucoRingError`` subclasses), never a bare ``KeyError``/``TypeError``/
``AttributeError``/``IndexError`` from deep inside; and a file error names the file it came from.

Inputs are valid documents with random mutations (fuzz_support.mutate), random junk documents,
and valid files truncated or corrupted at random byte positions. Seeded: the CI profile is
derandomized; ``FUZZ_EXAMPLES`` sets the example count.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from aruco_ring_localization.camera import CameraModel
from aruco_ring_localization.errors import ArucoRingError, ConfigError, MeasurementError
from aruco_ring_localization.marker_map import MarkerMap
from aruco_ring_localization.markers import MAX_MARKER_ID, parse_id_list, parse_size_overrides
from aruco_ring_localization.ring import CameraRing

from fuzz_support import FUZZ, junk, mutate
from helpers import CAM0_YAML, CONFIG, RING_YAML

with open(CAM0_YAML) as _f:
    CAM_DOC = yaml.safe_load(_f)
with open(RING_YAML) as _f:
    RING_DOC = yaml.safe_load(_f)
with open(CONFIG / "lab_scene.yaml") as _f:
    SCENE_DOC = yaml.safe_load(_f)

#: The ring file with each camera's intrinsics inline (mutations then reach the intrinsics too).
RING_INLINE_DOC = yaml.safe_load(yaml.safe_dump(RING_DOC))
for _c in RING_INLINE_DOC["cameras"]:
    with open(CONFIG / _c["camera_info"]) as _f:
        _c["camera_info"] = yaml.safe_load(_f)


def _map_doc() -> dict:
    """A valid map document (the simulated lab's true marker poses, or a hand-made one)."""
    try:
        from aruco_ring_localization.simulation.scene import Scene

        return Scene.default().truth_map("map").to_dict()
    except ImportError:  # pragma: no cover - the scene exists in main; keep this file independent
        return {"format_version": 1, "frame_id": "map", "reference_marker": 1, "markers": [
            {"id": 1, "size": 0.2, "translation": [1.0, 2.0, 1.0], "rotation": [0.5, 0.5, 0.5, 0.5]}]}


MAP_DOC = _map_doc()
MAP_DOC["reference_marker"] = MAP_DOC["markers"][0]["id"]


def _expect_own_error(fn, source=None):
    """Call ``fn``; a non-package exception fails the test; a ConfigError must name ``source``."""
    try:
        return fn()
    except ArucoRingError as exc:
        if source is not None and isinstance(exc, ConfigError):
            assert source in str(exc), f"error does not name the file {source!r}: {exc}"
        return exc


# --- mapped documents -----------------------------------------------------------------------------

def test_valid_documents_load():
    """The fuzz seeds themselves are valid (otherwise every mutation test would be vacuous)."""
    CameraModel.from_dict(CAM_DOC, source="cam.yaml")
    CameraRing.from_dict(RING_INLINE_DOC, source="ring.yaml")
    CameraRing.from_dict(RING_DOC, source=str(RING_YAML), base_dir=str(CONFIG))
    assert len(MarkerMap.from_dict(MAP_DOC, source="map.yaml")) == len(MAP_DOC["markers"])


@FUZZ
@given(st.data())
def test_fuzz_camera_from_dict(data):
    doc = mutate(data, CAM_DOC)
    result = _expect_own_error(lambda: CameraModel.from_dict(doc, source="fuzz_cam.yaml"), "fuzz_cam.yaml")
    if isinstance(result, CameraModel):
        # Whatever loads is usable: projecting a point in front of the camera gives finite pixels
        # or NaN (behind/outside), never an exception.
        result.project(np.array([[0.0, 0.0, 2.0]]))
        result.normalize(np.array([[result.cx, result.cy]]))


@FUZZ
@given(junk)
def test_fuzz_camera_from_junk(doc):
    _expect_own_error(lambda: CameraModel.from_dict(doc, source="junk_cam.yaml"), "junk_cam.yaml")


@FUZZ
@given(st.data())
def test_fuzz_camera_from_camera_info_fields(data):
    """CameraInfo message fields (as the message types allow them) -> MeasurementError only."""
    K = data.draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=12), label="K")
    if data.draw(st.booleans(), label="valid K"):
        K = [800.0, 0.0, 640.0, 0.0, 800.0, 480.0, 0.0, 0.0, 1.0]
    D = data.draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=9), label="D")
    model = data.draw(st.sampled_from(["", "plumb_bob", "rational_polynomial", "equidistant", "fisheye", "x"]))
    w = data.draw(st.integers(0, 2 ** 32 - 1), label="width")
    h = data.draw(st.integers(0, 2 ** 32 - 1), label="height")
    try:
        CameraModel.from_camera_info(K, D, model, w, h)
    except MeasurementError:
        pass


@FUZZ
@given(st.data())
def test_fuzz_ring_from_dict_inline(data):
    doc = mutate(data, RING_INLINE_DOC)
    result = _expect_own_error(lambda: CameraRing.from_dict(doc, source="fuzz_ring.yaml"), "fuzz_ring.yaml")
    if isinstance(result, CameraRing):
        for cam in result:
            assert cam.T_base_cam.shape == (4, 4)
            assert result.by_frame(cam.frame_id) is cam


@FUZZ
@given(st.data())
def test_fuzz_ring_from_dict_with_files(data):
    doc = mutate(data, RING_DOC)
    _expect_own_error(lambda: CameraRing.from_dict(doc, source="fuzz_ring.yaml", base_dir=str(CONFIG)),
                      "fuzz_ring.yaml")


@FUZZ
@given(junk)
def test_fuzz_ring_from_junk(doc):
    _expect_own_error(lambda: CameraRing.from_dict(doc, source="junk_ring.yaml", base_dir=str(CONFIG)),
                      "junk_ring.yaml")


@FUZZ
@given(st.data())
def test_fuzz_map_from_dict(data):
    doc = mutate(data, MAP_DOC)
    result = _expect_own_error(lambda: MarkerMap.from_dict(doc, source="fuzz_map.yaml"), "fuzz_map.yaml")
    if isinstance(result, MarkerMap):
        for e in result:
            c = result.corners(e.marker_id)
            assert c.shape == (4, 3) and np.all(np.isfinite(c)), (e.marker_id, c)
            assert e.size > 0
        # What loads saves and loads back the same.
        again = MarkerMap.from_dict(result.to_dict(), source="round trip")
        assert again.ids == result.ids


@FUZZ
@given(junk)
def test_fuzz_map_from_junk(doc):
    _expect_own_error(lambda: MarkerMap.from_dict(doc, source="junk_map.yaml"), "junk_map.yaml")


@FUZZ
@given(st.data())
def test_fuzz_scene_from_dict(data):
    from aruco_ring_localization.simulation.scene import Scene

    doc = mutate(data, SCENE_DOC)
    result = _expect_own_error(lambda: Scene.from_dict(doc, source="fuzz_scene.yaml"), "fuzz_scene.yaml")
    if isinstance(result, Scene):
        assert len(result.truth_map()) == len(result.markers)


@FUZZ
@given(junk)
def test_fuzz_scene_from_junk(doc):
    from aruco_ring_localization.simulation.scene import Scene

    _expect_own_error(lambda: Scene.from_dict(doc, source="junk_scene.yaml"), "junk_scene.yaml")


# --- raw file text ----------------------------------------------------------------------------

def _file_texts():
    from aruco_ring_localization.simulation.scene import Scene  # noqa: F401 (the loader must exist)

    return {
        "camera": (CAM0_YAML.read_text(), lambda p: CameraModel.from_yaml(p)),
        "ring": (yaml.safe_dump(RING_INLINE_DOC), lambda p: CameraRing.load(p)),
        "map": (yaml.safe_dump(MAP_DOC, default_flow_style=None), lambda p: MarkerMap.load(p)),
        "scene": ((CONFIG / "lab_scene.yaml").read_text(), lambda p: Scene.load(p)),
    }


FILE_TEXTS = _file_texts()


@FUZZ
@given(kind=st.sampled_from(sorted(FILE_TEXTS)), data=st.data())
def test_fuzz_file_bytes(kind, data):
    """Valid files truncated, with bytes replaced or inserted: ConfigError naming the file, or a load."""
    text, loader = FILE_TEXTS[kind]
    raw = bytearray(text.encode())
    op = data.draw(st.sampled_from(["truncate", "replace", "insert", "binary"]), label="op")
    if op == "truncate":
        raw = raw[: data.draw(st.integers(0, len(raw)), label="cut")]
    elif op == "binary":
        raw = bytearray(data.draw(st.binary(max_size=200), label="bytes"))
    else:
        for _ in range(data.draw(st.integers(1, 5), label="edits")):
            pos = data.draw(st.integers(0, max(len(raw) - 1, 0)), label="pos")
            byte = data.draw(st.sampled_from(list(b":-[]{}#'\"\n\t ,.0123456789e!&*|>%@`\xff\x00")), label="byte")
            if op == "replace" and raw:
                raw[pos] = byte
            else:
                raw.insert(pos, byte)
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, f"fuzz_{kind}.yaml")
        with open(path, "wb") as handle:
            handle.write(bytes(raw))
        _expect_own_error(lambda: loader(path), path)


# --- text parsers ----------------------------------------------------------------------------

id_text = st.text(alphabet="0123456789-,: .e+x\t", max_size=30) | st.text(max_size=20)


@FUZZ
@given(id_text)
def test_fuzz_parse_id_list(text):
    try:
        ids = parse_id_list(text, source="fuzz")
    except ConfigError as exc:
        assert "ignore_fiducials" in str(exc), exc
        return
    assert all(isinstance(i, int) and 0 <= i <= MAX_MARKER_ID for i in ids), sorted(ids)[:5]


@FUZZ
@given(st.lists(st.integers(0, MAX_MARKER_ID), max_size=6))
def test_parse_id_list_round_trip(ids):
    assert parse_id_list(",".join(map(str, ids))) == frozenset(ids)


@FUZZ
@given(id_text | st.builds(lambda a, b, L: f"{a}-{b}: {L}", st.integers(-5, 5000), st.integers(-5, 5000),
                           st.floats(allow_nan=True, allow_infinity=True)))
def test_fuzz_parse_size_overrides(text):
    try:
        sizes = parse_size_overrides(text, source="fuzz")
    except ConfigError as exc:
        assert "fiducial_len_override" in str(exc), exc
        return
    for i, L in sizes.items():
        assert 0 <= i <= MAX_MARKER_ID and np.isfinite(L) and L > 0, (i, L)


map_line = st.lists(st.sampled_from(["1", "-3", "0.5", "nan", "inf", "1e400", "x", "", "7.0", "-0.1", "12"]),
                    max_size=12).map(" ".join)


@FUZZ
@given(st.lists(map_line | st.text(max_size=30), max_size=6).map("\n".join),
       st.floats(allow_nan=True, allow_infinity=True))
def test_fuzz_fiducial_slam_text(text, size):
    try:
        m = MarkerMap.from_fiducial_slam_text(text, marker_size=size, source="fuzz_map.txt")
    except ArucoRingError as exc:
        if isinstance(exc, ConfigError) and np.isfinite(size) and size > 0:
            assert "fuzz_map.txt" in str(exc), exc
        return
    assert np.isfinite(size) and size > 0, f"a map with marker size {size} was accepted"
    for e in m:
        assert np.all(np.isfinite(m.corners(e.marker_id)))


@pytest.mark.parametrize("size", [0.0, -0.2, float("nan"), float("inf")])
def test_fiducial_slam_import_rejects_bad_marker_size(size):
    with pytest.raises(ArucoRingError):
        MarkerMap.from_fiducial_slam_text("1 0 0 0 0 0 0 0.01 3\n", marker_size=size, source="m.txt")


# --- anchors file and the map's anchors section (issue 13) ----------------------------------------

ANCHORS_DOC = {"frame_id": "plate", "anchors": [
    {"marker": 17, "position": [0.0, 3.1, 1.1], "std": 0.001, "instrument": "total station"},
    {"marker": 42, "position": [11.0, 3.6, 1.05], "std": [0.001, 0.002, 0.003]},
    {"marker": 95, "position": [4.0, 0.0, 0.9], "std": 0.001, "rotation": [0.5, 0.5, 0.5, 0.5],
     "rotation_std_deg": 0.05}]}
MAP_WITH_ANCHORS_DOC = dict(MAP_DOC, frame_convention="survey", anchors={
    "source": "a.yaml", "frame_id": "plate", "kind": "points", "points": [
        {"marker": 17, "surveyed": [0.0, 3.1, 1.1], "std": [0.001] * 3, "residual": [1e-4, 0.0, 0.0],
         "residual_sigmas": 0.1},
        {"marker": 42, "surveyed": [11.0, 3.6, 1.05], "std": [0.001] * 3, "mapped": False}]})


def test_valid_anchor_documents_load():
    from aruco_ring_localization.anchors import anchors_from_dict

    assert anchors_from_dict(ANCHORS_DOC, source="a.yaml").ids == [17, 42, 95]
    assert MarkerMap.from_dict(MAP_WITH_ANCHORS_DOC, source="map.yaml").anchors["kind"] == "points"


@FUZZ
@given(st.data())
def test_fuzz_anchors_from_dict(data):
    from aruco_ring_localization.anchors import AnchorSet, anchors_from_dict, check_anchor_report

    doc = mutate(data, ANCHORS_DOC)
    result = _expect_own_error(lambda: anchors_from_dict(doc, source="fuzz_anchors.yaml"), "fuzz_anchors.yaml")
    if isinstance(result, AnchorSet):
        for a in result.anchors:
            assert np.all(np.isfinite(a.position)) and np.all(a.position_std > 0)
        check_anchor_report({"points": []}, 5.0)


@FUZZ
@given(junk)
def test_fuzz_anchors_from_junk(doc):
    from aruco_ring_localization.anchors import anchors_from_dict

    _expect_own_error(lambda: anchors_from_dict(doc, source="junk_anchors.yaml"), "junk_anchors.yaml")


@FUZZ
@given(st.data())
def test_fuzz_map_anchors_section(data):
    from aruco_ring_localization.marker_map import check_map

    doc = mutate(data, MAP_WITH_ANCHORS_DOC)
    result = _expect_own_error(lambda: MarkerMap.from_dict(doc, source="fuzz_map.yaml"), "fuzz_map.yaml")
    if isinstance(result, MarkerMap):
        check_map(result)          # the sanity checks read the section: never a bare exception
