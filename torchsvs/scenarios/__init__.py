"""Seeded, batched simulators of maneuvering targets and the papers' scenarios."""

from torchsvs.scenarios.maneuver import (
    Controls,
    ManeuverBatch,
    ManeuverRanges,
    Segment,
    add_measurement_noise,
    random_maneuvers,
    segments_to_controls,
    simulate_controls,
    simulate_segments,
)
from torchsvs.scenarios.paper import Scenario, atc_scenario, complex_scenario, random_scenario
from torchsvs.scenarios.spvsf import ballistic_scenario, eha_scenario

__all__ = [
    "Controls",
    "ManeuverBatch",
    "ManeuverRanges",
    "Scenario",
    "Segment",
    "add_measurement_noise",
    "atc_scenario",
    "ballistic_scenario",
    "complex_scenario",
    "eha_scenario",
    "random_maneuvers",
    "random_scenario",
    "segments_to_controls",
    "simulate_controls",
    "simulate_segments",
]
