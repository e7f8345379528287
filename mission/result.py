"""The one result of a mission, the one per-user entry, the one horizontal error and status.

:class:`Result` is what a mission found: made by :func:`build_result` only, from an
:class:`estimator.types.Estimate` and the run's counts, by the mission (from the replay of its own
closed log, mission.replay.result_of_log), by `uavloc replay` (the same function, the same log)
and by a campaign's fast mode (no log: from its estimate). The CLI summary, `--json`,
report.json, report.html and a campaign's rows are renderings of it; :meth:`Result.to_document`
is its JSON (docs/design.md §11)::

    status, reason                 how the mission ended, judged against its final answer
                                   (mission.replay.status_of_answer; a log without an `end` record:
                                   "ok", "ambiguous" or "incomplete" of the estimate, :func:`result_status`)
    status_logged                  the status the log's `end` record holds (None: no such record);
                                   another than `status` where the answer does not support it
    users                          one entry per user, below
    flown_m, measurements, keyframes
    duration_s                     mission seconds, the log's header to its `end` record
    survey_s, hover_s, largest_gap_s   the `survey_time` event's, None when absent
    origin                         {lat_deg, lon_deg, alt_m} of the ENU frame, or None
    log                            the mission log's path, or None
    vehicles                       a fleet's only (docs/fleet.md): one entry per vehicle, below
    separation_breaches            a fleet's only: how often two vehicles in the air came closer
                                   than the separation (the `separation_lost` events)

Each vehicle of a fleet (:class:`VehicleResult`, from the events naming it)::

    id; ended                      how its part ended: "survey done: <reason>" or
                                   "return requested: <reason>" or "aborted: <error>"
    rtl_sent, landed               its safe end
    flown_m, survey_s, hover_s     its `survey_time` event's (None when absent)

Each user (:class:`UserResult`, :meth:`UserResult.to_dict`)::

    id, lat_deg, lon_deg, alt_m, enu_m            where (None when the user is not located)
    cov_en_m2, sigma_east_m, sigma_north_m         east-north covariance [m²] and its √diagonal [m]
    error_bound_95_m                               semi-major axis of the 95 % ellipse [m]
    measurements, ambiguous                        when known
    bias_m                                         when range biases were estimated and the user is
                                                   located (mean range bias [m]; where a user's bias
                                                   was selected off, the value it is held at: 0, or
                                                   with bias_held "sawtooth" an untracked sawtooth's mean)
    clock_sawtooth                                 {period_s, amplitude_m} where a UE clock sawtooth
                                                   was tracked (then bias_m is its mean, A/2)
    noise_scale                                    when estimated: how much noisier than the assumed
                                                   σ(d) this user's ranges were
    nlos_shift_m                                   when estimated: the shift [m] an NLoS excess from
                                                   one side can make unseen, in cov_en_m2 (0: no NLoS)
    error_m, truth                                 when the truth is known (simulation)

Floats are finite or None (JSON has no NaN). Pure: numpy and the origin's pymap3d conversion.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.types import error_bound_95_m

#: how a mission ended (Result.status), named once
STATUS_TARGET = "target_reached"
STATUS_BUDGET = "budget_spent"
STATUS_NO_LEG = "no_feasible_leg"
STATUS_FLOOR = "floor_reached"  # the bounds stopped shrinking above the target (GPS floor)
STATUS_RETURNED = "returned"  # a safety condition ended the survey early
STATUS_ABORTED = "aborted"  # an error ended the mission (RTL sent when airborne)
STATUS_INTERRUPTED = "interrupted"  # cancelled / Ctrl-C (RTL sent when airborne)
#: the survey stopped at its target, but the final answer bounds a user beyond it (mission.replay.status_of_answer)
STATUS_TARGET_MISSED = "target_missed"
#: the statuses of a mission that ended normally (the command exits 0 when every user is located)
NORMAL_END = (STATUS_TARGET, STATUS_FLOOR, STATUS_BUDGET, STATUS_NO_LEG, STATUS_RETURNED, STATUS_TARGET_MISSED)


def status_of_planner_reason(reason: str) -> str:
    """The status of a survey the planner ended (planner.types.PlanResult.reason)."""
    return {"target reached": STATUS_TARGET, "floor reached": STATUS_FLOOR,
            "budget spent": STATUS_BUDGET}.get(reason, STATUS_NO_LEG)


def horizontal_error_m(users_enu_m: np.ndarray, truth_enu_m: np.ndarray) -> np.ndarray:
    """(...,) east-north distance ||(e, n)_estimate − (e, n)_truth|| [m]; NaN where either is
    unknown. users_enu_m, truth_enu_m: (..., 3) or (..., 2), broadcast against each other."""
    u = np.asarray(users_enu_m, dtype=float)
    t = np.asarray(truth_enu_m, dtype=float)
    # e_k = sqrt((ê_k − e_k)² + (n̂_k − n_k)²)
    return np.linalg.norm(u[..., :2] - t[..., :2], axis=-1)


def result_status(estimate: Any) -> str:
    """"ok" when every user of the estimate (users_enu_m (K, 3), ambiguous (K,)) is located without
    ambiguity; "ambiguous" or "incomplete" otherwise (replay's document and the report)."""
    if not np.all(np.isfinite(estimate.users_enu_m)):
        return "incomplete"
    if np.any(estimate.ambiguous):
        return "ambiguous"
    return "ok"


def finite_or_none(x: Any) -> float | None:
    """A finite float, or None (JSON has no NaN or infinity)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class ClockSawtooth:
    """A tracked UE clock sawtooth: period [s] and amplitude [m] (its mean, A/2, is the bias)."""

    period_s: float
    amplitude_m: float


@dataclass(frozen=True)
class TruthPosition:
    """A user's true position (simulation): ENU [m] about the result's origin, and geodetic."""

    enu_m: tuple[float, float, float]
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class UserResult:
    """One user's result (the module docstring's entry). Position fields are None when the user is
    not located; measurements/ambiguous None when unknown; bias_m, noise_scale, nlos_shift_m None
    when not estimated (or the user not located); truth None when unknown; error_m [m] None when the
    truth or the position is unknown. cov_en_m2: ((σ_ee², σ_en), (σ_ne, σ_nn²)) [m²]."""

    id: str
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    enu_m: tuple[float, float, float] | None = None
    cov_en_m2: tuple[tuple[float, float], tuple[float, float]] | None = None
    error_bound_95_m: float | None = None
    measurements: int | None = None
    ambiguous: bool | None = None
    bias_m: float | None = None
    clock_sawtooth: ClockSawtooth | None = None
    noise_scale: float | None = None
    nlos_shift_m: float | None = None
    truth: TruthPosition | None = None
    error_m: float | None = None

    @property
    def located(self) -> bool:
        return self.enu_m is not None

    @property
    def sigma_east_m(self) -> float | None:
        c = self.cov_en_m2
        return math.sqrt(c[0][0]) if c is not None and c[0][0] >= 0 else None

    @property
    def sigma_north_m(self) -> float | None:
        c = self.cov_en_m2
        return math.sqrt(c[1][1]) if c is not None and c[1][1] >= 0 else None

    def to_dict(self) -> dict[str, Any]:
        """The JSON entry (module docstring): optional keys appear when known."""
        entry: dict[str, Any] = {
            "id": self.id, "lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m,
            "enu_m": None if self.enu_m is None else list(self.enu_m),
            "cov_en_m2": None if self.cov_en_m2 is None else [list(r) for r in self.cov_en_m2],
            "sigma_east_m": self.sigma_east_m, "sigma_north_m": self.sigma_north_m,
            "error_bound_95_m": self.error_bound_95_m,
        }
        if self.measurements is not None:
            entry["measurements"] = self.measurements
        if self.ambiguous is not None:
            entry["ambiguous"] = self.ambiguous
        for key in ("noise_scale", "nlos_shift_m", "bias_m"):
            if getattr(self, key) is not None:
                entry[key] = getattr(self, key)
        if self.clock_sawtooth is not None:
            entry["clock_sawtooth"] = {"period_s": self.clock_sawtooth.period_s,
                                       "amplitude_m": self.clock_sawtooth.amplitude_m}
        if self.truth is not None:
            entry["error_m"] = self.error_m
            t = self.truth
            entry["truth"] = {"lat_deg": t.lat_deg, "lon_deg": t.lon_deg, "alt_m": t.alt_m, "enu_m": list(t.enu_m)}
        return entry


def users_of(
    user_ids: Sequence[str],
    origin: Origin | None,
    users_enu_m: np.ndarray | None,
    cov_en_m2: np.ndarray | None,
    *,
    measurements: Sequence[int] | np.ndarray | None = None,
    ambiguous: Sequence[bool] | np.ndarray | None = None,
    bias_m: np.ndarray | None = None,
    clock_sawtooth: Sequence[ClockSawtooth | None] | None = None,
    noise_scale: np.ndarray | None = None,
    nlos_shift_m: np.ndarray | None = None,
    truth_enu_m: np.ndarray | None = None,
) -> tuple[UserResult, ...]:
    """The :class:`UserResult` of K users from plain arrays.

    users_enu_m: (K, 3) ENU about `origin` [m] (NaN rows: not located), or None when nothing is
    estimated (then `origin` may be None too); cov_en_m2: (K, 2, 2) [m²] or None; measurements (K,),
    ambiguous (K,), bias_m (K,), clock_sawtooth (K,), noise_scale (K,), nlos_shift_m (K,),
    truth_enu_m (K, 3): optional (bias, noise scale, shift and sawtooth kept where the user is located).
    """
    k_users = len(user_ids)
    users = (np.full((k_users, 3), np.nan) if users_enu_m is None or origin is None
             else np.asarray(users_enu_m, dtype=float).reshape(k_users, 3))
    cov = (np.full((k_users, 2, 2), np.nan) if cov_en_m2 is None
           else np.asarray(cov_en_m2, dtype=float).reshape(k_users, 2, 2))
    located = np.all(np.isfinite(users), axis=1)
    if origin is not None and np.any(located):
        lat, lon, alt = (np.atleast_1d(a) for a in origin.enu_to_lla(np.where(located[:, None], users, 0.0)))
    else:
        lat = lon = alt = np.full(k_users, np.nan)
    bound = error_bound_95_m(cov)
    err = None if truth_enu_m is None else horizontal_error_m(users, truth_enu_m)
    truth = None if truth_enu_m is None else np.asarray(truth_enu_m, dtype=float).reshape(k_users, 3)

    def located_value(values, k: int) -> float | None:
        return None if values is None or not located[k] else finite_or_none(values[k])

    out = []
    for k, uid in enumerate(user_ids):
        c = cov[k]
        truth_k = None
        if truth is not None and origin is not None and np.all(np.isfinite(truth[k])):
            tl = origin.enu_to_lla(truth[k])
            truth_k = TruthPosition(tuple(float(x) for x in truth[k]), float(tl[0]), float(tl[1]), float(tl[2]))
        out.append(UserResult(
            id=uid,
            lat_deg=float(lat[k]) if located[k] else None,
            lon_deg=float(lon[k]) if located[k] else None,
            alt_m=float(alt[k]) if located[k] else None,
            enu_m=tuple(float(x) for x in users[k]) if located[k] else None,
            cov_en_m2=tuple(tuple(float(x) for x in row) for row in c) if np.all(np.isfinite(c)) else None,
            error_bound_95_m=finite_or_none(bound[k]),
            measurements=None if measurements is None else int(measurements[k]),
            ambiguous=None if ambiguous is None else bool(ambiguous[k]),
            bias_m=located_value(bias_m, k),
            clock_sawtooth=None if clock_sawtooth is None or not located[k] else clock_sawtooth[k],
            noise_scale=located_value(noise_scale, k),
            nlos_shift_m=located_value(nlos_shift_m, k),
            truth=truth_k,
            error_m=None if err is None else finite_or_none(err[k]),
        ))
    return tuple(out)


def users_of_estimate(estimate: Any, origin: Origin | None, user_ids: Sequence[str],
                      truth_enu_m: np.ndarray | None = None) -> tuple[UserResult, ...]:
    """:func:`users_of` an `estimator.types.Estimate` (None: no user located): a tracked clock
    sawtooth's amplitude is its estimated b and its mean A/2 the bias; a bias selected off is the
    value it is held at."""
    if estimate is None:
        return users_of(user_ids, origin, None, None, truth_enu_m=truth_enu_m)
    k = len(user_ids)
    bias = None
    saw: list[ClockSawtooth | None] | None = None
    if estimate.bias_m is not None:
        bias = np.array(estimate.bias_m, dtype=float)
        st = estimate.state
        on = None if st is None else st.bias_on
        clocks = (None if st is None else st.clock) or [None] * k
        saw = [None] * k
        for j in range(k):
            if clocks[j] is not None and np.isfinite(bias[j]):
                # a tracked clock sawtooth: its amplitude is the estimated b; its mean A/2 the bias
                saw[j] = ClockSawtooth(float(clocks[j].period_s), float(bias[j]))
                bias[j] *= 0.5
            elif on is not None and not on[j]:
                # selected off: the value it is held at
                bias[j] = 0.0 if st.bias_held_m is None else float(st.bias_held_m[j])
    scale = None if estimate.state is None else estimate.state.noise_scale
    shift = None if estimate.state is None else estimate.state.nlos_shift_m
    return users_of(
        user_ids, origin, estimate.users_enu_m,
        np.array([estimate.cov_en_m2(j) for j in range(k)]).reshape(k, 2, 2),
        measurements=estimate.n_ranges, ambiguous=estimate.ambiguous, bias_m=bias,
        clock_sawtooth=saw, noise_scale=None if scale is None else np.asarray(scale, dtype=float),
        nlos_shift_m=None if shift is None else np.asarray(shift, dtype=float), truth_enu_m=truth_enu_m,
    )


def user_entries(user_ids: Sequence[str], origin: Origin | None, users_enu_m: np.ndarray | None,
                 cov_en_m2: np.ndarray | None, **optional: Any) -> list[dict]:
    """The JSON entries of :func:`users_of` (same arguments)."""
    return [u.to_dict() for u in users_of(user_ids, origin, users_enu_m, cov_en_m2, **optional)]


def user_entries_of_estimate(estimate: Any, origin: Origin | None, user_ids: Sequence[str],
                             truth_enu_m: np.ndarray | None = None) -> list[dict]:
    """The JSON entries of :func:`users_of_estimate`."""
    return [u.to_dict() for u in users_of_estimate(estimate, origin, user_ids, truth_enu_m)]


@dataclass(frozen=True)
class VehicleResult:
    """One vehicle's part of a fleet's mission (the module docstring)."""

    id: str
    ended: str
    rtl_sent: bool
    landed: bool
    flown_m: float | None = None
    survey_s: float | None = None
    hover_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "ended": self.ended, "rtl_sent": self.rtl_sent, "landed": self.landed,
                "flown_m": finite_or_none(self.flown_m), "survey_s": finite_or_none(self.survey_s),
                "hover_s": finite_or_none(self.hover_s)}


#: the events that end a vehicle's part, and how VehicleResult.ended names them
_ENDS = {"stop": "survey done", "return": "return requested", "abort": "aborted"}


def vehicles_of_events(vehicle_ids: Sequence[str], events: Sequence[dict]) -> tuple[tuple[VehicleResult, ...], int]:
    """A fleet's vehicles (one :class:`VehicleResult` each, in `vehicle_ids` order) and its
    separation breaches, from the mission log's `event` records (each naming its `vehicle` by
    index; absent: vehicle 0). The last `stop`, `return`, `abort` or `target_in_final_answer` of a
    vehicle before its survey's `survey_time`, or a `return` requested during the survey and logged
    after it (`in_survey`), says how its part ended (a survey the final answer
    sent on ends again later; a return requested on the way home changes nothing); its last
    `survey_time` gives its metres and seconds."""
    n = len(vehicle_ids)
    ended: list[str | None] = [None] * n  # how its survey ended, once its `survey_time` closed it
    pending: list[str | None] = [None] * n  # the latest end before that
    rtl, landed = [False] * n, [False] * n
    survey: list[dict] = [{} for _ in range(n)]
    breaches = 0
    for e in events:
        kind = e.get("kind")
        if kind == "separation_lost":
            breaches += 1
            continue
        v = e.get("vehicle", 0)
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v < n:
            continue
        if kind == "return" and e.get("in_survey") is True and ended[v] is not None:
            # requested during the survey, logged after its survey_time: it ended the survey
            reason = e.get("reason")
            ended[v] = f"{_ENDS[kind]}: {reason if isinstance(reason, str) else e.get('message', '')}"
        elif kind in _ENDS and ended[v] is None:
            reason = e.get("reason")
            pending[v] = f"{_ENDS[kind]}: {reason if isinstance(reason, str) else e.get('message', '')}"
        elif kind == "target_in_final_answer" and ended[v] is None:
            pending[v] = "survey done: target reached"  # the final answer turned its end into the target
        elif kind == "rtl":
            rtl[v] = True
        elif kind == "landed":
            landed[v] = True
        elif kind == "survey_time":
            survey[v] = e
            ended[v] = ended[v] or pending[v]

    def num(d: dict, key: str) -> float | None:
        x = d.get(key)
        return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else None

    return tuple(VehicleResult(vehicle_ids[v], ended[v] or pending[v] or "did not survey", rtl[v], landed[v],
                               num(survey[v], "flown_m"), num(survey[v], "survey_s"), num(survey[v], "hover_s"))
                 for v in range(n)), breaches


@dataclass(frozen=True)
class Result:
    """What one mission found (the module docstring): made by :func:`build_result` only.

    status, reason: how it ended; users: one :class:`UserResult` per user, in the mission's order;
    flown_m: survey metres flown [m]; measurements: ranges used; keyframes: keyframes used;
    duration_s: mission seconds from the log's header to its end (None when unknown);
    survey_s, hover_s, largest_gap_s: the survey's seconds, those spent hovering, the longest
    without a range [s] (None when unknown); origin: the ENU frame's origin (None: never known);
    log_path: the mission log (None: none).
    """

    status: str
    reason: str
    users: tuple[UserResult, ...]
    flown_m: float
    measurements: int
    keyframes: int
    duration_s: float | None = None
    survey_s: float | None = None
    hover_s: float | None = None
    largest_gap_s: float | None = None
    origin: Origin | None = None
    log_path: Path | None = None
    vehicles: tuple[VehicleResult, ...] = ()
    separation_breaches: int | None = None
    status_logged: str | None = None

    def status_note(self) -> str | None:
        """What to warn about when the log recorded another status than its answer supports, else None."""
        if self.status_logged is None or self.status_logged == self.status:
            return None
        where = f"{self.log_path}: " if self.log_path is not None else ""
        return (f"{where}the log recorded status {self.status_logged}, but its final answer supports "
                f"{self.status} ({self.reason}): the status printed is the answer's")

    @property
    def user_ids(self) -> list[str]:
        return [u.id for u in self.users]

    def not_located(self) -> list[str]:
        """Ids of the users without a position, or with one a mirror position explains as well."""
        return [u.id for u in self.users if not u.located or bool(u.ambiguous)]

    @property
    def ok(self) -> bool:
        """The mission ended normally and located every user (else the command exits non-zero)."""
        return self.status in NORMAL_END and not self.not_located()

    def users_enu_m(self) -> np.ndarray:
        """(K, 3) estimated users [m] (NaN rows: not located)."""
        return np.array([u.enu_m if u.located else (np.nan,) * 3 for u in self.users], float).reshape(-1, 3)

    def cov_en_m2(self) -> np.ndarray:
        """(K, 2, 2) east-north covariances [m²] (NaN where unknown)."""
        return np.array([np.full((2, 2), np.nan) if u.cov_en_m2 is None else u.cov_en_m2 for u in self.users],
                        float).reshape(-1, 2, 2)

    def truth_enu_m(self) -> np.ndarray | None:
        """(K, 3) true users [m] (NaN rows where unknown), or None when no user's truth is known."""
        if all(u.truth is None for u in self.users):
            return None
        return np.array([(np.nan,) * 3 if u.truth is None else u.truth.enu_m for u in self.users],
                        float).reshape(-1, 3)

    def error_m(self) -> np.ndarray | None:
        """(K,) horizontal error of each user [m] (NaN: not located) when the truth is known."""
        truth = self.truth_enu_m()
        return None if truth is None else horizontal_error_m(self.users_enu_m(), truth)

    def to_document(self) -> dict[str, Any]:
        """The result's JSON document (module docstring; docs/design.md §11)."""
        return {
            "status": self.status, "reason": self.reason, "users": [u.to_dict() for u in self.users],
            "flown_m": finite_or_none(self.flown_m), "measurements": self.measurements,
            "keyframes": self.keyframes, "duration_s": finite_or_none(self.duration_s),
            "survey_s": finite_or_none(self.survey_s), "hover_s": finite_or_none(self.hover_s),
            "largest_gap_s": finite_or_none(self.largest_gap_s),
            "origin": None if self.origin is None else self.origin.to_dict(),
            "log": None if self.log_path is None else str(self.log_path), "status_logged": self.status_logged,
        } | ({"vehicles": [v.to_dict() for v in self.vehicles], "separation_breaches": self.separation_breaches}
             if self.vehicles else {})


def build_result(*, status: str, reason: str, user_ids: Sequence[str], estimate: Any, origin: Origin | None,
                 flown_m: float, measurements: int, keyframes: int, truth_enu_m: np.ndarray | None = None,
                 duration_s: float | None = None, survey_s: float | None = None, hover_s: float | None = None,
                 largest_gap_s: float | None = None, log_path: Path | None = None,
                 vehicles: Sequence[VehicleResult] = (), separation_breaches: int | None = None,
                 status_logged: str | None = None) -> Result:
    """The one constructor of a :class:`Result`: the users of `estimate` (an
    `estimator.types.Estimate`, None: nothing located) about `origin`, against truth_enu_m (K, 3)
    when known, and the run's facts as given."""
    users = users_of_estimate(estimate if origin is not None else None, origin, list(user_ids), truth_enu_m)
    return Result(status=status, reason=reason, users=users, flown_m=float(flown_m), measurements=int(measurements),
                  keyframes=int(keyframes), duration_s=None if duration_s is None else float(duration_s),
                  survey_s=survey_s, hover_s=hover_s, largest_gap_s=largest_gap_s, origin=origin,
                  log_path=None if log_path is None else Path(log_path), vehicles=tuple(vehicles),
                  separation_breaches=separation_breaches, status_logged=status_logged)


def format_users_table(users: Sequence[UserResult]) -> str:
    """Human-readable lines: where each user is."""
    lines = []
    for u in users:
        if not u.located:
            lines.append(f"  {u.id}: not located ({u.measurements or 0} ranges)")
            continue
        e, n, _ = u.enu_m
        bound = u.error_bound_95_m
        s = (f"  {u.id}: lat {u.lat_deg:.7f}  lon {u.lon_deg:.7f}  alt {u.alt_m:.1f} m  "
             f"(E {e:+.1f} m, N {n:+.1f} m)  95% bound {float('nan') if bound is None else bound:.2f} m")
        if u.error_m is not None:
            s += f"  error {u.error_m:.2f} m"
        if u.nlos_shift_m:
            # the part of the bound no survey shrinks (estimator.nlos_shift)
            s += f"  [NLoS from one side: {u.nlos_shift_m:.1f} m shift in the bound]"
        if u.ambiguous:
            s += "  [mirror ambiguity unresolved]"
        lines.append(s)
    return "\n".join(lines)


def format_result(result: Result) -> str:
    """The human-readable summary of a result: one line, the users' table, the log."""
    lines = [f"mission {result.status} ({result.reason}): {result.measurements} ranges, {result.keyframes} "
             f"keyframes, {result.flown_m:.0f} m flown"
             + ("" if result.duration_s is None else f" in {result.duration_s:.0f} s"),
             format_users_table(result.users)]
    for v in result.vehicles:
        flown = "" if v.flown_m is None else f", {v.flown_m:.0f} m flown"
        home = "landed" if v.landed else "RTL sent, landing not confirmed" if v.rtl_sent else "NO RTL SENT"
        lines.append(f"  vehicle {v.id}: {v.ended}{flown}; {home}")
    if result.vehicles:
        lines.append(f"  separation breaches: {result.separation_breaches or 0}")
    if result.log_path is not None:
        lines.append(f"mission log: {result.log_path}")
    return "\n".join(lines)
