"""The closed loop still produces the golden trajectories (``record.py``) to 1e-9: positions (m),
headings and steering angles (rad) at every step of the first 2 s, and every gear exactly."""

from __future__ import annotations

import numpy as np
import pytest

from platoon_opt.vehicle import wrap_angle
from tests.golden.record import ALLOCATORS, FIELDS, SCENARIOS, SEEDS, path_of, run


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("label", list(ALLOCATORS))
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_the_model_reproduces_its_golden_trajectory(scenario, label, seed):
    golden = np.load(path_of(scenario, label, seed))
    now = run(scenario, label, seed)
    assert set(golden.files) == set(FIELDS)
    for field in FIELDS:
        assert now[field].shape == golden[field].shape
        if field == "gear":
            np.testing.assert_array_equal(now[field], golden[field])
        elif field == "theta":  # wrapped to (-pi, pi]: pi and -pi + 1e-15 are 1e-15 apart
            assert np.max(np.abs(wrap_angle(now[field] - golden[field]))) <= 1e-9
        else:
            np.testing.assert_allclose(now[field], golden[field], rtol=0, atol=1e-9, err_msg=field)
