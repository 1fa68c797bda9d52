"""Ablation variants: modelling choices the paper leaves open, applied to a scenario."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

from platoon_opt.scenarios import Scenario


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
    """

    name: str
    title: str = ""
    gear_hysteresis_deg: float | None = None
    ahead_reference: str | None = None
    dt_scale: float = 1.0

    def apply(self, scenario: Scenario) -> Scenario:
        """The scenario with this variant's choices."""
        changes: dict[str, Any] = {}
        if self.gear_hysteresis_deg is not None:
            limits = replace(scenario.limits, gear_hysteresis=math.radians(self.gear_hysteresis_deg))
            changes["limits"] = limits
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
