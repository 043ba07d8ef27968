"""Seeded, batched simulators of maneuvering targets and the papers' scenarios (road targets
included: :mod:`torchsvs.scenarios.road`; DME navigation: :mod:`torchsvs.scenarios.dme`)."""

from torchsvs.scenarios.dme import DMEScenario, dme_scenario
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
from torchsvs.scenarios.road import (
    CURVE_ROAD_I_POINTS,
    CURVE_ROAD_II_POINTS,
    CircularRoad,
    RoadScenario,
    SpeedProfile,
    StraightRoad,
    circular_road_scenario,
    curve_road_scenario,
    road_scenario,
    speed_profile,
    straight_road_scenario,
)
from torchsvs.scenarios.spline import ArcLengthSpline, NaturalCubicSpline
from torchsvs.scenarios.spvsf import ballistic_scenario, eha_scenario

__all__ = [
    "ArcLengthSpline",
    "CURVE_ROAD_II_POINTS",
    "CURVE_ROAD_I_POINTS",
    "CircularRoad",
    "NaturalCubicSpline",
    "RoadScenario",
    "SpeedProfile",
    "StraightRoad",
    "circular_road_scenario",
    "curve_road_scenario",
    "road_scenario",
    "speed_profile",
    "straight_road_scenario",
    "Controls",
    "DMEScenario",
    "ManeuverBatch",
    "ManeuverRanges",
    "Scenario",
    "Segment",
    "add_measurement_noise",
    "atc_scenario",
    "ballistic_scenario",
    "complex_scenario",
    "dme_scenario",
    "eha_scenario",
    "random_maneuvers",
    "random_scenario",
    "segments_to_controls",
    "simulate_controls",
    "simulate_segments",
]
