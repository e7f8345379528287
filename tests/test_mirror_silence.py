"""Silence refutes a mirror (estimator.silence): with a cell of limited reach, keyframes within reach
of a user's mirror position that did not range it prove it is not there.

The world: a user 300 m north of a straight east–west track (50 m up, every 4 m), a cell of 400 m
slant reach. The whole track is within reach of the user, so ranges from it cannot tell it from its
mirror 300 m south; after the track the UAV flies south-east, beyond reach of the user, to within
ρ R of the mirror, where it hears nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.noise import NoiseModel
from estimator.problem import check_params, pack_keyframes
from estimator.silence import SILENT_MIN_KEYFRAMES, SILENT_REACH_SHARE, cell_rows, silence_refutes
from estimator.types import Keyframe, SolverParams
from uavloc.errors import EstimatorError

NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)
REACH_M = 400.0
PARAMS = SolverParams(estimate_bias=False, track_clock=False, coverage_m=REACH_M)
TRUTH = np.array([0.0, 300.0, 0.0])
MIRROR = np.array([0.0, -300.0, 0.0])
UP = np.zeros(1)
ALT_M = 50.0


def _kf(rng, pos, t, ranged: bool, vehicle: int = 0) -> Keyframe:
    pos = np.asarray(pos, float)
    gps = pos + rng.normal(0.0, NOISE.sigma_gps_m, 3)
    if not ranged:
        return Keyframe(gps, np.zeros(0, int), np.zeros(0), t_s=t, vehicle=vehicle)
    r = np.linalg.norm(pos - TRUTH) + rng.normal(0.0, NOISE.range_s0_m)
    return Keyframe(gps, np.array([0]), np.array([r]), t_s=t, vehicle=vehicle)


def _track(rng, every: int = 1, vehicle: int = 0, t0: float = 0.0) -> list[Keyframe]:
    """The straight track, all of it within reach of the user; the user ranged at every `every`-th
    keyframe (a gNB whose rounds take the users in turn)."""
    xs = np.arange(-240.0, 241.0, 4.0)
    out = [_kf(rng, (x, 0.0, ALT_M), t0 + i, i % every == 0, vehicle) for i, x in enumerate(xs)]
    assert all(np.linalg.norm(np.array([x, 0.0, ALT_M]) - TRUTH) < REACH_M for x in xs)
    return out


def _near(centre, m: int, t0: float, vehicle: int = 0, seed: int = 5) -> list[Keyframe]:
    """m keyframes 4 m apart that range nothing, on a north–south leg 200 m east of `centre` (the user
    or its mirror), from 150 m short of it (towards the track) away from the track: within ρ R of it,
    beyond R of its reflection."""
    rng = np.random.default_rng(seed)
    sign = math.copysign(1.0, centre[1])
    out = []
    for i in range(m):
        pos = np.array([200.0, centre[1] - sign * (150.0 - 4.0 * i), ALT_M])
        assert np.linalg.norm(pos - centre) <= SILENT_REACH_SHARE * REACH_M
        assert np.linalg.norm(pos - centre * [1.0, -1.0, 1.0]) > REACH_M
        out.append(_kf(rng, pos, t0 + i, False, vehicle))
    return out


def _solve(keyframes, params=PARAMS, start=None):
    return solve_batch(keyframes, 1, UP, NOISE, params, init_users_enu_m=None if start is None else start[None])


def _at(est, where) -> bool:
    return float(np.linalg.norm(est.users_enu_m[0, :2] - where[:2])) < 5.0


def test_a_straight_track_leaves_the_user_ambiguous():
    est = _solve(_track(np.random.default_rng(1)), replace(PARAMS, coverage_m=math.inf))
    assert est.ambiguous[0]
    # one of the two is the truth, the other its reflection across the track
    assert _at(est, TRUTH) or _at(est, MIRROR)
    assert np.linalg.norm(est.mirror_enu_m[0, :2] - est.users_enu_m[0, :2] * [1.0, -1.0]) < 5.0


@pytest.mark.parametrize("start", [None, TRUTH, MIRROR], ids=["grid", "truth", "mirror"])
def test_silence_within_reach_of_the_mirror_refutes_it(start):
    """Whichever side the solve starts on, it ends at the truth, unambiguous: a refuted mirror is no
    ambiguity, a refuted estimate is flipped to its mirror (the grid start lands on the mirror)."""
    kfs = _track(np.random.default_rng(1)) + _near(MIRROR, 12, 200.0)
    est = _solve(kfs, start=start)
    assert not est.ambiguous[0]
    assert np.all(np.isnan(est.mirror_enu_m[0]))
    assert _at(est, TRUTH), est.users_enu_m[0]
    assert np.isfinite(est.error_bound_95_m()[0])


def test_the_refutation_needs_silent_min_keyframes():
    track = _track(np.random.default_rng(1))
    few = _solve(track + _near(MIRROR, SILENT_MIN_KEYFRAMES - 1, 200.0), start=TRUTH)
    assert few.ambiguous[0] and np.all(np.isfinite(few.mirror_enu_m[0]))
    enough = _solve(track + _near(MIRROR, SILENT_MIN_KEYFRAMES, 200.0), start=TRUTH)
    assert not enough.ambiguous[0] and _at(enough, TRUTH)


@pytest.mark.parametrize("start", [TRUTH, MIRROR], ids=["truth", "mirror"])
def test_silence_of_another_vehicles_cell_at_the_true_side_refutes_nothing(start):
    """A fleet: vehicle 1 flies within reach of the truth and never ranges the user, which is vehicle
    0's cell's UE. Its silence says nothing: the user stays ambiguous, wherever the solve starts. The
    same keyframes as vehicle 0's would have refuted the truth (the rule's vehicle condition is what
    keeps it)."""
    track = _track(np.random.default_rng(1))
    other = _near(TRUTH, 12, 200.0, vehicle=1)
    est = _solve(track + other, start=start)
    assert est.ambiguous[0] and _at(est, start)
    own = _solve(track + [replace(kf, vehicle=0) for kf in other], start=start)
    assert not own.ambiguous[0] and _at(own, MIRROR)


def test_an_unlimited_reach_never_refutes():
    kfs = _track(np.random.default_rng(1)) + _near(MIRROR, 40, 200.0)
    for start in (TRUTH, MIRROR):
        est = _solve(kfs, replace(PARAMS, coverage_m=math.inf), start=start)
        assert est.ambiguous[0] and _at(est, start)
    prob = pack_keyframes(kfs, 1, UP, NOISE, replace(PARAMS, coverage_m=math.inf))
    est_ref, mir_ref = silence_refutes(prob, [0], TRUTH[None], MIRROR[None])
    assert not est_ref[0] and not mir_ref[0]


def test_a_user_answering_some_keyframes_needs_more_silence():
    """Rounds that take the users in turn: the user is ranged at one track keyframe in 4, so a
    keyframe without it is weak evidence (q̂ = 31/122): the track's own silent keyframes refute
    nothing, 12 near the mirror neither; −2 S ln(1 − q̂) ≥ χ²_amb = 9 needs S ≥ 16."""
    track = _track(np.random.default_rng(1), every=4)
    q = 31 / 122
    need = math.ceil(PARAMS.ambiguity_chi2 / (-2.0 * math.log1p(-q)))
    assert need == 16
    assert _solve(track + _near(MIRROR, need - 1, 200.0), start=TRUTH).ambiguous[0]
    est = _solve(track + _near(MIRROR, need, 200.0), start=TRUTH)
    assert not est.ambiguous[0] and _at(est, TRUTH)


def test_the_mission_publishes_the_refuted_mirror_as_unambiguous():
    """The mission's estimate (estimator.refresh): its batch refreshes, warm ones too, apply the rule."""
    from estimator.refresh import RefreshedEstimator

    ref = RefreshedEstimator(1, UP, NOISE, PARAMS)
    for kf in _track(np.random.default_rng(1)) + _near(MIRROR, 12, 200.0):
        ref.add_keyframe(kf)
    est = ref.refresh()
    assert est.state.warm_started
    assert not est.ambiguous[0] and _at(est, TRUTH)


def test_a_cell_serves_the_user_only_while_no_other_cell_does():
    """Keyframes that count as silence for a user (cell_rows): those of a vehicle that ranged it, whose
    nearest ranges of the user in time before and after are its own. The user is vehicle 0's UE at
    t 0–9, vehicle 1's at 20–29, vehicle 0's again at 40–45."""
    ranged = {0: list(range(0, 10)) + list(range(40, 46)), 1: list(range(20, 30))}
    kfs = []
    for v in (0, 1, 2):
        for t in range(0, 60, 1):
            hit = t in ranged.get(v, [])
            kfs.append(Keyframe(np.array([float(t), 10.0 * v, ALT_M]), np.array([0] if hit else [], int),
                                np.array([100.0] if hit else []), t_s=float(t), vehicle=v))
    prob = pack_keyframes(kfs, 1, UP, NOISE, PARAMS)
    assert prob.vehicle is not None
    cell = cell_rows(prob, [0])[0]
    t, v = prob.t_s, prob.vehicle
    # vehicle 0: its own ranges and after them, before the other cell took the user, after its
    # last range; not from its range at 9 to its range at 40 (the other cell's in between)
    assert np.array_equal(t[cell & (v == 0)], np.r_[np.arange(0, 10), np.arange(40, 60)])
    # vehicle 1: only its own service
    assert np.array_equal(t[cell & (v == 1)], np.arange(20, 30))
    # vehicle 2 never ranged the user
    assert not np.any(cell & (v == 2))
    # one vehicle: every keyframe
    one = pack_keyframes([kf for kf in kfs if kf.vehicle == 0], 1, UP, NOISE, PARAMS)
    assert one.vehicle is None and cell_rows(one, [0]).all()


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, True, "400"])
def test_coverage_must_be_positive_or_inf(bad):
    with pytest.raises(EstimatorError, match="coverage_m"):
        check_params(replace(PARAMS, coverage_m=bad))
    check_params(replace(PARAMS, coverage_m=math.inf))


def test_the_mission_estimates_with_its_cells_reach_and_replay_reads_it_back(tmp_path):
    from mission.config import example_mission_path, load_mission
    from mission.estimation import mission_solver_params, solver_params_header
    from mission.log import read_mission_log
    from mission.replay import solver_params_from_header

    mission = load_mission(example_mission_path())
    params = mission_solver_params(mission)
    assert params.coverage_m == mission.gnb.coverage_m and math.isfinite(params.coverage_m)
    log = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"
    lines = log.read_text().splitlines(keepends=True)
    for p, want in ((params, params.coverage_m), (replace(params, coverage_m=math.inf), math.inf)):
        head = json.loads(lines[0])
        # the header as the controller writes it: JSON without infinities
        head["config"]["solver"] = solver_params_header(p)
        out = tmp_path / "solver.jsonl"
        out.write_text(json.dumps(head, allow_nan=False) + "\n" + "".join(lines[1:]))
        got = solver_params_from_header(read_mission_log(out))
        assert got.coverage_m == want and got == p
