"""``aruco_ring check-config`` on a map with survey measurements: their residuals, the check."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.anchors import anchors_from_dict, measurement_report
from aruco_ring_localization.cli import main
from aruco_ring_localization.errors import MapSanityError
from aruco_ring_localization.marker_map import MarkerEntry, MarkerMap

from helpers import RING_YAML


@pytest.mark.parametrize("measured, ok", [(5.0, True), (5.05, False)])
def test_a_map_whose_distance_is_off_fails_the_check(tmp_path, capsys, measured, ok):
    """Markers 3 and 7 are 5 m apart in the map; a tape of 5.05 m (1 mm std) is 50 sigma off."""
    entries = [MarkerEntry(i, geo.make_transform(np.eye(3), [x, 0.0, 1.0]), 0.2, np.full(3, 0.002), np.zeros(3), 40)
               for i, x in ((3, 0.0), (7, 5.0))]
    m = MarkerMap(entries, reference_marker=3, method="refined")
    survey = anchors_from_dict(yaml.safe_load(f"distances: [{{from: {{marker: 3}}, to: {{marker: 7}}, "
                                              f"distance: {measured}, std: 0.001}}]"), source="tape.yaml")
    m.quality["survey_measurements"] = measurement_report(survey.measurements,
                                                          {e.marker_id: e.T_map_marker for e in m}, lambda i: 0.2)
    path = str(tmp_path / "map.yaml")
    if ok:
        m.save(path)
    else:   # the save refuses it (check_map); a file written otherwise (by hand, another tool)
        with pytest.raises(MapSanityError, match="measurements: distances"):
            m.save(path)
        with open(path, "w") as f:
            yaml.safe_dump(m.to_dict(), f, sort_keys=False)
    assert main(["check-config", "--ring", str(RING_YAML), "--map", path]) == (0 if ok else 1)
    out = capsys.readouterr().out
    assert "distance distances[0]: marker 3 corner centre to marker 7 corner centre" in out
    assert ("check failed: measurements: distances[0]" in out) != ok, out
