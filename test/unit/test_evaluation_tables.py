"""evaluation.tables: the paper's Tables I and II keep signs and state their frame; CSV; the paper's figures."""
from __future__ import annotations

import numpy as np

from aruco_ring_localization.evaluation import tables
from aruco_ring_localization.evaluation.stops import StopError


def _rows():
    return [StopError("1", np.array([1.0, 2.0, 0.0]), np.array([1.012, 1.985, np.radians(0.25)]), 4, 10.0, 12.0),
            StopError("2", np.array([3.0, 2.0, np.pi / 2]), np.array([2.99, 2.004, np.pi / 2 - np.radians(0.1)]))]


def test_table1_keeps_signs_and_names_its_frame():
    md = tables.position_table_markdown(_rows(), reference_name="ground truth", frame="lab frame")
    assert "lab frame" in md.splitlines()[0] and "ground truth" in md.splitlines()[0], md
    assert "| 1 | +1.200 | -1.500 | 1.921 |" in md, md
    assert "| 2 | -1.000 | +0.400 | 1.077 |" in md, md
    assert "Median Euclidean error 1.499 cm" in md, md


def test_table2_and_csv():
    md = tables.orientation_table_markdown(_rows(), frame="lab frame")
    assert "+0.250" in md and "-0.100" in md and "lab frame" in md, md
    csv = tables.stops_csv(_rows()).splitlines()
    assert csv[0] == ",".join(tables.CSV_COLUMNS) and len(csv) == 3, csv
    assert csv[1].split(",")[10:12] == ["1.2000", "-1.5000"], csv[1]


def test_write_tables(tmp_path):
    paths = tables.write_tables(str(tmp_path), _rows(), [], frame="map frame")
    assert sorted(paths) == ["table1_csv", "table1_md"], paths
    assert "map frame" in (tmp_path / "table1.md").read_text()


def test_paper_statistics_come_from_its_tables():
    p = tables.paper_statistics()
    # the paper's text: median 3.10 cm, max 17.27 cm, mean |yaw| 1.9 deg, max 4.5 deg (vs gmapping)
    assert round(p["position_cm_median"], 2) == 3.10 and round(p["position_cm_max"], 2) == 17.27, p
    assert round(p["yaw_deg_mean_abs"], 2) == 1.90 and p["yaw_deg_max_abs"] == 4.501, p
