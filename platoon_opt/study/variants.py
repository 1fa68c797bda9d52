"""Ablation variants: modelling choices the paper leaves open, applied to a scenario."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from platoon_opt.scenarios import Scenario
from platoon_opt.validation import positive
from platoon_opt.vehicle import INTEGRATIONS


@dataclass(frozen=True)
class Variant:
    """A modelling choice the paper leaves open, applied to a scenario (the ablation).

    Attributes:
        name: file-safe name ("base", "no-hysteresis", ...).
        title: name in the report.
        gear_hysteresis_deg: replaces ``VehicleLimits.gear_hysteresis`` (degrees) if given.
        ahead_reference: replaces ``AvoidanceParams.ahead_reference`` ("heading" or
            "travel") if given.
        dt_scale: multiplies the scenario's time step.
        start_offset: if given (m, >= 0), the platoon's initial centre is placed this far west
            (-x: the paper's platoon starts "on the left-hand side") of the target's start, as a
            scenario file's ``target.start_offset = [start_offset, 0]`` does; 0 starts it on the
            target. Not for an explicit formation (``Scenario.positions``).
        steering_gain: replaces ``VehicleLimits.steering_gain`` (K_alpha, 1/s; K_alpha dt = 1
            is deadbeat) if given.
        integration: replaces ``VehicleLimits.integration`` ("arc" or "euler") if given.

    Raises:
        ValueError: a bad ``start_offset``, ``steering_gain``, ``integration`` or ``dt_scale``,
            one line naming the field and the value.
    """

    name: str
    title: str = ""
    gear_hysteresis_deg: float | None = None
    ahead_reference: str | None = None
    dt_scale: float = 1.0
    start_offset: float | None = None
    steering_gain: float | None = None
    integration: str | None = None

    def __post_init__(self) -> None:
        positive("Variant.dt_scale", self.dt_scale)
        if self.start_offset is not None:
            positive("Variant.start_offset", self.start_offset, allow_zero=True)
        if self.steering_gain is not None:
            positive("Variant.steering_gain", self.steering_gain)
        if self.integration is not None and self.integration not in INTEGRATIONS:
            raise ValueError(f"Variant.integration must be 'arc' or 'euler', got {self.integration!r}")

    def apply(self, scenario: Scenario) -> Scenario:
        """The scenario with this variant's choices.

        Raises:
            ValueError: ``start_offset`` given for an explicit formation (one line).
        """
        changes: dict[str, Any] = {}
        limits: dict[str, Any] = {}
        if self.gear_hysteresis_deg is not None:
            limits["gear_hysteresis"] = math.radians(self.gear_hysteresis_deg)
        if self.steering_gain is not None:
            limits["steering_gain"] = self.steering_gain
        if self.integration is not None:
            limits["integration"] = self.integration
        if limits:
            changes["limits"] = replace(scenario.limits, **limits)
        if self.start_offset is not None:
            if scenario.positions is not None:
                raise ValueError(
                    f"Variant.start_offset must be left out for {scenario.name}, whose formation is "
                    f"explicit (no centre to move), got {self.start_offset!r}"
                )
            start = np.asarray(scenario.target.at(0.0)[0], dtype=float)
            changes["center"] = start - np.array([self.start_offset, 0.0])
        if self.ahead_reference is not None:
            changes["avoidance"] = replace(scenario.avoidance, ahead_reference=self.ahead_reference)
        if self.dt_scale != 1.0:
            changes["dt"] = scenario.dt * self.dt_scale
        return replace(scenario, **changes) if changes else scenario

    def affects(self, scenario: Scenario) -> bool:
        """False for variants that change the Eq. 6 "ahead" test in a scenario without
        obstacles: the test never fires there, so the variant repeats another one."""
        return self.ahead_reference is None or len(scenario.obstacles) > 0


BASE = Variant("base", "as in the scenario file")


# Modelling choices of docs/model.md: without the gear rule's hysteresis and with Eq. 6's "ahead"
# on the direction of travel the base controller chatters; one at a time, both together (the most
# literal reading of the paper), and half the time step.
ABLATION_VARIANTS = (
    Variant("no-hysteresis", "gear rule without hysteresis", gear_hysteresis_deg=0.0),
    Variant("travel-ahead", 'Eq. 6 "ahead" on the travel direction', ahead_reference="travel"),
    Variant(
        "no-hysteresis-travel",
        "both of the above",
        gear_hysteresis_deg=0.0,
        ahead_reference="travel",
    ),
    Variant("half-dt", "dt / 2", dt_scale=0.5),
)
