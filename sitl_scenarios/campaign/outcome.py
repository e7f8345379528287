"""What one run measured, whatever flew it (fast or full mode), and the accuracy bookkeeping both share."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimator.types import CHI2_2DOF_95, error_bound_95_m
from mission.result import Result


@dataclass
class Outcome:
    """One run's measurements.

    metres_to: target [m] → metres flown when every user's printed 95 % error bound (NLoS shift
        included) first was within it, as the stop rule judges (planner.stop.targets_reached;
        absent: never); seconds_to: target → survey seconds then [s], hover included;
        error_at: target → mean true horizontal error [m] at that moment;
    plan_times_s: compute time of every plan() call [s]; violations: constraint breaks found by an
        independent check of each leg (fast mode);
    result: the run's :class:`mission.result.Result` (full mode: the mission's; fast mode: built by
        the same constructor from its final estimate), of which end ("status: reason"), flown_m,
        keyframes, final_error_m and final_bound95_m ((K,) per user at the end [m], NaN where the
        user was not located) are the row's rendering (:meth:`Outcome.take_result`);
    final_nees: (K,) eᵀ Σ⁻¹ e of each user's final east-north error e and covariance Σ (NaN where
        never located: inside the 95 % ellipse at ≤ χ²₂(0.95) = 5.99, the 99.9 % one at ≤ 13.8);
        inside95: share of (estimate, user) pairs
        after a user's first estimate whose true error lies inside its own 95 % ellipse;
        nlos_share: share of ranges whose line of sight a building blocked; estimator_errors: what
        the estimator reported failing during the run (the mission went on: estimator.refresh drops a
        failed online part, the flight logs an `estimator_error` event), in order; hover_s: survey
        seconds the vehicle stood waiting (full mode: the mission's `survey_time` event; fast mode:
        each plan's compute time beyond the lead the mission plans ahead with, PLAN_AHEAD_S); survey_s:
        the survey's mission seconds, hover included; events: what befell the vehicles (fast mode: a
        vehicle that left the survey, when and why), in order.
    """

    metres_to: dict = field(default_factory=dict)
    seconds_to: dict = field(default_factory=dict)
    hover_s: float = 0.0
    survey_s: float = 0.0
    error_at: dict = field(default_factory=dict)
    plan_times_s: list = field(default_factory=list)
    violations: list = field(default_factory=list)
    flown_m: float = 0.0
    end: str = ""
    keyframes: int = 0
    final_error_m: list = field(default_factory=list)
    final_bound95_m: list = field(default_factory=list)
    final_nees: list = field(default_factory=list)
    inside95: float = math.nan
    nlos_share: float = math.nan
    estimator_errors: list = field(default_factory=list)
    events: list = field(default_factory=list)
    result: Result | None = None

    def take_result(self, result: Result) -> Outcome:
        """Hold the run's result, and render the row's columns that are its facts."""
        self.result = result
        self.end = f"{result.status}: {result.reason}"
        self.flown_m = float(result.flown_m)
        self.keyframes = int(result.keyframes)
        err = result.error_m()
        self.final_error_m = [math.nan] * len(result.users) if err is None else [float(v) for v in err]
        self.final_bound95_m = [math.nan if u.error_bound_95_m is None else float(u.error_bound_95_m)
                                for u in result.users]
        return self


class AccuracyTrack:
    """Follows a run's estimates against the truth: target crossings and 95 % ellipse coverage.

    truth_enu_m: (K, 3) true users [m, ENU]; targets_m: accuracy targets [m], descending.
    """

    def __init__(self, truth_enu_m: np.ndarray, targets_m: tuple[float, ...]):
        self.truth_en = np.asarray(truth_enu_m, float)[:, :2]
        self.pending = sorted(targets_m, reverse=True)
        self.metres_to: dict = {}
        self.seconds_to: dict = {}
        self.error_at: dict = {}
        self.inside = 0
        self.seen = 0
        self.error_m = np.full(len(self.truth_en), np.nan)
        self.bound95_m = np.full(len(self.truth_en), np.nan)
        self.nees = np.full(len(self.truth_en), np.nan)

    def update(self, users_en_m: np.ndarray, cov_en_m2: np.ndarray, at_m: float, at_s: float = math.nan) -> None:
        """One estimate: users_en_m (K, 2) [m] (NaN rows: not located), cov_en_m2 (K, 2, 2) [m²]
        (the covariance the mission prints), metres flown and survey seconds when it was made."""
        users_en_m = np.asarray(users_en_m, float)
        cov = np.asarray(cov_en_m2, float)
        ok = np.all(np.isfinite(users_en_m), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
        e = users_en_m - self.truth_en
        self.error_m = np.where(ok, np.linalg.norm(e, axis=1), np.nan)
        self.bound95_m = np.where(ok, error_bound_95_m(cov), np.inf)
        # the user's NEES eᵀ Σ⁻¹ e, NaN where not located (like error_m)
        self.nees = np.full(len(self.truth_en), np.nan)
        if np.any(ok):
            nees = np.einsum("ki,ki->k", e[ok], np.linalg.solve(cov[ok], e[ok][:, :, None])[:, :, 0])
            self.nees[ok] = nees
            # inside the ellipse: eᵀ Σ⁻¹ e ≤ χ²₂(0.95)
            self.inside += int(np.sum(nees <= CHI2_2DOF_95))
            self.seen += int(np.sum(ok))
        # the stop rule's test: every user's printed bound within T
        bound = float(np.max(self.bound95_m)) if len(self.bound95_m) else math.inf
        while self.pending and bound <= self.pending[0]:
            tgt = self.pending.pop(0)
            self.metres_to[tgt] = float(at_m)
            self.seconds_to[tgt] = float(at_s)
            self.error_at[tgt] = float(np.mean(self.error_m))
        self.bound95_m = np.where(ok, self.bound95_m, np.nan)

    def fill(self, out: Outcome) -> Outcome:
        out.metres_to, out.error_at = dict(self.metres_to), dict(self.error_at)
        out.seconds_to = dict(self.seconds_to)
        out.final_error_m = [float(v) for v in self.error_m]
        out.final_bound95_m = [float(v) for v in self.bound95_m]
        out.final_nees = [float(v) for v in self.nees]
        out.inside95 = self.inside / self.seen if self.seen else math.nan
        return out
