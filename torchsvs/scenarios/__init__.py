"""Seeded, batched simulators of maneuvering targets and the papers' scenarios."""

from torchsvs.scenarios.maneuver import Segment, add_measurement_noise, simulate_segments
from torchsvs.scenarios.paper import Scenario, atc_scenario

__all__ = ["Scenario", "Segment", "add_measurement_noise", "atc_scenario", "simulate_segments"]
