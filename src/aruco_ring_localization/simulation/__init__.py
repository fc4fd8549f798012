"""Simulated hall and camera ring: scene files, corners/image simulation, robot motion, laser scan."""
from __future__ import annotations

from .ring_sim import RingSimulator, VisibleMarker, perturb_ring
from .scene import Scene, SceneMarker

__all__ = ["Scene", "SceneMarker", "RingSimulator", "VisibleMarker", "perturb_ring"]
