"""Radio model of the simulated gNB: geometry, quantization and the error statistics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.ranging import C_MPS, range_m_from_raw, ta_step_s
from sitl_scenarios.radio import RadioModel, line_of_sight_blocked, point_in_polygon
from sitl_scenarios.scenario import BuildingConfig, RadioConfig, scenario_from_dict, user_tables
from uavloc.errors import ScenarioError, SimulatorError

SQUARE = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]
BLD = BuildingConfig(footprint_enu_m=SQUARE, height_m=20.0)


def make_scenario(radio: dict | None = None, users: list[dict] | None = None, buildings=None):
    data = {
        "name": "t",
        "seed": 3,
        **user_tables(users or [{"id": "a", "rnti": 0x4601, "east_m": 0.0, "north_m": 0.0}]),
        # ideal UEs unless a test asks for a clock sawtooth (commercial UEs are the default)
        "radio": {"ue_sawtooth_amplitude_m": 0.0, **(radio or {})},
    }
    if buildings is not None:
        data["buildings"] = buildings
    return scenario_from_dict(data)


@pytest.mark.parametrize(
    ("p", "inside"),
    [((5, 5), True), ((-1, 5), False), ((11, 5), False), ((5, 11), False), ((9.9, 0.1), True)],
)
def test_point_in_polygon_square(p, inside):
    assert point_in_polygon(p, SQUARE) is inside


def test_point_in_polygon_concave():
    ell = [[0, 0], [10, 0], [10, 2], [2, 2], [2, 10], [0, 10]]
    assert point_in_polygon((1, 5), ell)
    assert not point_in_polygon((5, 5), ell)


@pytest.mark.parametrize(
    ("uav", "user", "blocked"),
    [
        ((-20, 5, 10), (30, 5, 0), True),  # straight through below the roof
        ((-20, 5, 60), (30, 5, 0), False),  # passes above the roof: z at e=0 is 36, at e=10 is 24
        ((-20, 5, 40), (30, 5, 0), True),  # z at e=10 is 16 < 20: cuts the far wall
        ((-20, 20, 5), (30, 20, 0), False),  # passes beside
        ((5, 5, 100), (5, 5, 0), True),  # user indoors, UAV straight above
        ((-5, -5, 100), (20, -5, 0), False),
        ((-20, 5, 20), (30, 5, 20), False),  # grazes the roof exactly
        ((-20, -20, 5), (30, 30, 0), True),  # diagonal through corners
    ],
)
def test_line_of_sight_blocked_table(uav, user, blocked):
    assert line_of_sight_blocked(uav, user, [BLD]) is blocked


def test_no_buildings_never_blocked():
    assert not line_of_sight_blocked((0, 0, 1), (5, 5, 0), [])


def test_roundtrip_through_ranging_recovers_range_to_quantization():
    sc = make_scenario({"s0_m": 1e-6, "mu": 1, "fs_hz": 46.08e6, "oversampling": 8})
    model = RadioModel(sc, np.random.default_rng(0))
    for d in (5.0, 77.0, 150.0, 999.0):
        raw = model.measure(0, (d, 0.0, 0.0), 0.0)
        assert raw is not None
        assert 0 <= raw.srs_peak * 8 == round(raw.srs_peak * 8)
        r = range_m_from_raw(raw.ta, raw.mu, raw.srs_peak, raw.fs_hz)
        q = C_MPS / (2 * 46.08e6 * 8)
        assert abs(r - d) <= q / 2 + 1e-3
        # TA is the floor of RTT / step: the residual is less than one step
        assert raw.srs_peak / raw.fs_hz < ta_step_s(1) + 1 / (46.08e6 * 8)


def test_no_answer_beyond_coverage():
    model = RadioModel(make_scenario({"coverage_m": 100.0}), np.random.default_rng(0))
    assert model.measure(0, (99.0, 0, 0), 0.0) is not None
    assert model.measure(0, (101.0, 0, 0), 0.0) is None


def test_same_seed_same_numbers_and_unknown_user_raises():
    sc = make_scenario()
    a = [RadioModel(sc, np.random.default_rng(5)).measure(0, (30, 40, 10), t) for t in range(3)]
    b = [RadioModel(sc, np.random.default_rng(5)).measure(0, (30, 40, 10), t) for t in range(3)]
    assert a == b
    m = RadioModel(sc, np.random.default_rng(5))
    with pytest.raises(SimulatorError):
        m.measure(3, (0, 0, 0), 0.0)
    with pytest.raises(SimulatorError):
        m.measure_rnti(0x1234, (0, 0, 0), 0.0)


def test_sawtooth_rises_then_resets():
    sc = make_scenario(users=[{"id": "a", "rnti": 1, "east_m": 0.0, "north_m": 0.0,
                               "sawtooth_amplitude_m": 6.0, "sawtooth_period_s": 10.0}])
    m = RadioModel(sc, np.random.default_rng(1))
    t = np.linspace(0, 30, 3001)
    s = np.array([m.sawtooth_m(0, ti) for ti in t])
    assert s.min() >= 0 and s.max() < 6.0
    drops = np.flatnonzero(np.diff(s) < -3)
    assert len(drops) == 3  # one reset per period
    assert np.all(np.diff(s)[np.diff(s) > -3] > 0)  # otherwise rising


# ---------------------------------------------------------------------------------------------
# statistics: the simulated errors follow the configured model


def _errors(model: RadioModel, uav, n: int, t0: float = 0.0, dt: float = 0.0):
    out = []
    for i in range(n):
        raw = model.measure(0, uav, t0 + i * dt)
        assert raw is not None
        out.append((range_m_from_raw(raw.ta, raw.mu, raw.srs_peak, raw.fs_hz) - raw.true_range_m, raw))
    return np.array([e for e, _ in out]), [r for _, r in out]


def test_error_mean_zero_and_spread_grows_with_distance():
    radio = {"s0_m": 2.0, "a_m": 0.5, "b_per_m": 0.004, "coverage_m": 2000.0}
    model = RadioModel(make_scenario(radio), np.random.default_rng(11))
    n = 4000
    for d in (50.0, 400.0, 800.0):
        err, _ = _errors(model, (d, 0.0, 30.0), n)
        true_d = float(np.hypot(d, 30.0))
        sigma = 2.0 + 0.5 * np.exp(0.004 * true_d)
        # sample mean within 4 standard errors; sample std within 5 %
        assert abs(err.mean()) < 4 * sigma / np.sqrt(n) + 0.05
        assert abs(err.std(ddof=1) / sigma - 1) < 0.05


def test_sawtooth_mean_is_half_amplitude_bias():
    sc = make_scenario({"s0_m": 0.5}, users=[{"id": "a", "rnti": 1, "east_m": 0.0, "north_m": 0.0,
                                              "sawtooth_amplitude_m": 8.0, "sawtooth_period_s": 20.0}])
    model = RadioModel(sc, np.random.default_rng(2))
    # 4000 samples spread over 50 periods: mean → A/2 = 4 m
    err, raws = _errors(model, (100.0, 0.0, 40.0), 4000, dt=0.25)
    assert abs(err.mean() - 4.0) < 0.15
    saw = np.array([r.sawtooth_m for r in raws])
    assert abs(saw.mean() - 4.0) < 0.1 and saw.max() < 8.0


def test_nlos_excess_only_where_a_building_blocks():
    bld = {"footprint_enu_m": [[40.0, -10.0], [60.0, -10.0], [60.0, 10.0], [40.0, 10.0]], "height_m": 30.0}
    sc = make_scenario({"s0_m": 1.0, "nlos_excess_mean_m": 15.0}, buildings=[bld])
    model = RadioModel(sc, np.random.default_rng(4))
    n = 3000
    # blocked: UAV behind the building at low height
    err_b, raws_b = _errors(model, (100.0, 0.0, 10.0), n)
    assert all(r.nlos for r in raws_b)
    assert abs(err_b.mean() - 15.0) < 4 * np.sqrt(15.0**2 + 1) / np.sqrt(n)
    assert np.mean([r.nlos_excess_m for r in raws_b]) == pytest.approx(15.0, rel=0.06)
    # clear: same distance but high above the roof, and beside the building
    for uav in ((100.0, 0.0, 200.0), (0.0, 100.0, 10.0)):
        err_c, raws_c = _errors(model, uav, n)
        assert not any(r.nlos for r in raws_c)
        assert all(r.nlos_excess_m == 0.0 for r in raws_c)
        assert abs(err_c.mean()) < 0.15


def test_nlos_excess_mean_zero_config_gives_no_excess():
    bld = {"footprint_enu_m": SQUARE, "height_m": 30.0}
    sc = make_scenario({"nlos_excess_mean_m": 0.0}, users=[{"id": "a", "rnti": 1, "east_m": 5.0,
                                                             "north_m": 5.0}], buildings=[bld])
    raw = RadioModel(sc, np.random.default_rng(0)).measure(0, (50, 50, 5), 0.0)
    assert raw is not None and raw.nlos and raw.nlos_excess_m == 0.0


def test_radio_config_defaults_are_used():
    sc = make_scenario()
    assert sc.radio == dataclasses.replace(RadioConfig(), ue_sawtooth_amplitude_m=0.0)


def test_users_are_commercial_ues_with_a_clock_sawtooth_by_default():
    sc = scenario_from_dict({"name": "t", "seed": 3, **user_tables([
        {"id": "a", "rnti": 0x4601, "east_m": 0.0, "north_m": 0.0},
        {"id": "b", "rnti": 0x4602, "east_m": 5.0, "north_m": 0.0, "sawtooth_amplitude_m": 0.0},
        {"id": "c", "rnti": 0x4603, "east_m": 9.0, "north_m": 0.0, "sawtooth_amplitude_m": 4.0,
         "sawtooth_period_s": 7.0}])})
    model = RadioModel(sc, np.random.default_rng(1))
    assert model.sawtooth_params(0) == (RadioConfig().ue_sawtooth_amplitude_m, RadioConfig().ue_sawtooth_period_s)
    assert model.sawtooth_params(1)[0] == 0.0 and model.sawtooth_m(1, 3.0) == 0.0
    assert model.sawtooth_params(2) == (4.0, 7.0)
    saw = [model.sawtooth_m(0, t) for t in np.arange(0.0, 60.0, 0.1)]
    assert 0.0 <= min(saw) < 1.0 and 11.0 < max(saw) <= 12.0


@pytest.mark.parametrize("bad", [{"ue_sawtooth_amplitude_m": -1.0}, {"ue_sawtooth_period_s": 0.0}])
def test_bad_commercial_ue_sawtooth_rejected(bad):
    with pytest.raises(ScenarioError, match="ue_sawtooth"):
        make_scenario(radio=bad)
