"""Errors against a reference: trajectories, maps, stops, the paper's tables and figures (no ROS).

One module per concept:

- :mod:`.trajectories`: TUM files, time association, alignment (``none`` / ``se2`` / ``se3``) and
  the absolute pose error, on evo (``PoseTrajectory3D``, ``file_interface``, ``sync``,
  ``geometry.umeyama_alignment``, ``metrics.APE``); planar pose pairs for the tables;
- :mod:`.maps`: a marker map against the truth, in the map's own frame definition (the strict
  convention) or after a best-fit SE(3) alignment (a diagnostic);
- :mod:`.stops`: where the reference stood still, and the errors at each stop;
- :mod:`.tables`: the paper's Table I (position) and Table II (orientation), markdown and CSV;
- :mod:`.figures`: the paper's figures (matplotlib, Agg backend);
- :mod:`.report`: the demo's report (its stops, summary.json, the console summary);
- :mod:`.comparison`: the live comparison with a reference (the ``comparison`` node's core).

The convention everywhere: errors are estimate minus reference, and nothing is fitted unless
asked; a fitted alignment absorbs a constant frame error and is reported as a diagnostic.
"""
from __future__ import annotations
