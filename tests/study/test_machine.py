"""The machine information shared by the bench, the soak and the timing experiments."""

from __future__ import annotations

import json
import math

from platoon_opt.study.machine import load_average, machine


def test_machine_names_the_cpu_and_the_versions():
    info = machine()
    assert set(info) == {"cpu", "cores", "python", "numpy", "clarabel", "osqp", "platform"}
    assert json.loads(json.dumps(info)) == info
    assert isinstance(info["cpu"], str) and info["cores"] >= 1


def test_load_average_is_a_number():
    load = load_average()
    assert math.isnan(load) or load >= 0.0
