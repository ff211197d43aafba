"""Simulated recordings with ground truth: ``tagtrail simulate`` (see :func:`simulate`)."""

from __future__ import annotations

from tagtrail.sim.scenarios import RECORDINGS, SCENARIOS, SimOptions
from tagtrail.sim.simulate import simulate

__all__ = ["RECORDINGS", "SCENARIOS", "SimOptions", "simulate"]
