"""The estimate a mission acts on: the online estimator, refreshed by batch solves over every
keyframe seen.

The online estimator (estimator.online) costs constant time a keyframe, but what it has
marginalized stays linearized where it was, and it does not track a UE's clock sawtooth (a fit needs
the residuals of whole periods; estimator.batch._track_clocks). On a commercial UE its estimate can
sit metres from the batch answer with an ellipse that excludes it, and the stop rule, the planner
and the operator would all act on that ellipse. So the estimate a mission publishes is the batch
solution (what `uavloc replay` and the mission's final answer compute), refreshed

    every max(REFRESH_MIN_KEYFRAMES, ⌊REFRESH_SHARE · n⌋) keyframes (n: keyframes seen so far),

so that the refreshes cost O(1/REFRESH_SHARE) batch-keyframe-solves per keyframe (a batch over n
keyframes costs O(n): amortized constant time per keyframe), and at once whenever the caller's
`confirm` predicate holds on the online estimate (e.g. the stop rule: a target that only the online
estimate reaches is checked by the batch before anyone acts on it), at most every
CONFIRM_MIN_KEYFRAMES keyframes. Between refreshes the last batch estimate stands (it lags by
at most REFRESH_SHARE of the keyframes); before the first one, the online estimate.

A refresh is warm (estimator.batch._warm_solve: started from the last refresh, keeping its NLoS
probabilities, noise scales, bias selection and clock sawtooths: one robust solve) except when the
keyframes have grown by COLD_GROWTH since the last cold one, or a user started since: then cold
(every choice re-made, as in the final answer, but started from the last refresh's users). The
cold refreshes cost Σ cost(n_j) ≤ cost(n) · COLD_GROWTH / (COLD_GROWTH − 1) over a mission.

A refresh on which `confirm` holds is solved again from nothing (no warm start, no initial guess)
before it is published, unless it was so solved: what the caller acts on (the stop rule: "target
reached") is then the final answer's own computation over the same keyframes (solve_batch), not one
that can differ from it (seen: 3.51 m on a warm refresh, 4.15 m in the final answer, against a 4 m
target; 3.99 m on a cold refresh started from the last users, 4.20 m in the final answer).

Keyframes that queued up while the estimator was busy are added together and published once
(`add_keyframes`): at most one refresh for all of them, so an estimator that falls behind (a
loaded machine, a sped-up simulation) catches up instead of lagging further.

A fleet's keyframes (Keyframe.vehicle) are estimated by the batch refreshes alone: the online
window links each keyframe to the one before it, another vehicle's in a fleet.

Each published Estimate says which it is: Estimate.source is SOURCE_BATCH or SOURCE_ONLINE, and
Estimate.keyframes_used the number of keyframes it is the answer for.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from collections.abc import Callable, Sequence

import numpy as np

from estimator.batch import solve_batch
from estimator.noise import NoiseModel
from estimator.online import OnlineEstimator
from estimator.problem import check_keyframe
from estimator.types import SOURCE_BATCH, SOURCE_ONLINE, Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

log = logging.getLogger(__name__)

#: a batch refresh every ⌊REFRESH_SHARE · n⌋ keyframes, REFRESH_MIN_KEYFRAMES at least
REFRESH_SHARE = 0.05
REFRESH_MIN_KEYFRAMES = 3
#: a refresh is cold when the keyframes have grown by this factor since the last cold one
COLD_GROWTH = 2.0
#: a refresh asked for by `confirm` comes at most this often [keyframes]
CONFIRM_MIN_KEYFRAMES = 2



class _OnlineFailed(EstimatorError):
    """The online part failed on a keyframe that was kept (RefreshedEstimator._add)."""


class RefreshedEstimator:
    """OnlineEstimator plus batch refreshes (module docstring).

    add_keyframe(kf, confirm=None) -> the Estimate to act on. The online estimator runs on every
    keyframe (its estimate is `online_estimate`; online=False leaves it out: no confirm then, and
    the first keyframe is a refresh); the batch solves are warm or cold (module docstring).
    """

    def __init__(
        self, n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
        params: SolverParams = SolverParams(),  # noqa: B008
        refresh_share: float = REFRESH_SHARE, online: bool = True,
    ):
        if not (isinstance(refresh_share, int | float) and 0.0 <= refresh_share <= 1.0):
            raise EstimatorError(f"refresh_share must be within [0, 1], got {refresh_share!r}")
        # without the online estimator (online=False: nobody asks to confirm, e.g. a replay's
        # history) every keyframe is only validated and kept
        self._online = OnlineEstimator(n_users, user_up_m, noise, params) if online else None
        self._args = (int(n_users), np.asarray(user_up_m, dtype=float), noise, params)
        self._share = float(refresh_share)
        self._keyframes: list[Keyframe] = []
        self._batch: Estimate | None = None
        self._batch_at = 0  # keyframes seen at the last refresh
        self._batch_exact = False  # the last refresh was solve_batch of its keyframes from nothing
        self._cold_at = 0  # ... at the last cold one
        self._confirm_at = -CONFIRM_MIN_KEYFRAMES
        self.n_refreshes = 0
        self.online_failure: str | None = None

    @property
    def online_estimate(self) -> Estimate | None:
        return None if self._online is None else self._online.estimate

    @property
    def batch_estimate(self) -> Estimate | None:
        """The last batch refresh, None before the first."""
        return self._batch

    @property
    def n_keyframes_seen(self) -> int:
        return len(self._keyframes)

    def refresh_due(self) -> bool:
        """True when the schedule asks for a batch refresh now."""
        n = len(self._keyframes)
        return n > 0 and n - self._batch_at >= max(REFRESH_MIN_KEYFRAMES, math.floor(self._share * n))

    def add_keyframe(self, kf: Keyframe, confirm: Callable[[Estimate], bool] | None = None) -> Estimate:
        """Add one keyframe; return the estimate to act on (module docstring).

        confirm(online_estimate) -> True asks for a refresh now (rate-limited). Raises
        EstimatorError on a malformed keyframe (nothing is added)."""
        with contextlib.suppress(_OnlineFailed):  # logged; the keyframe is kept
            self._add(kf)
        return self._publish(confirm)

    def add_keyframes(
        self, keyframes: Sequence[Keyframe], confirm: Callable[[Estimate], bool] | None = None,
    ) -> tuple[Estimate | None, list[EstimatorError]]:
        """Add keyframes that queued up while the estimator was busy, then publish once: at most one
        refresh however many arrived, so an estimator that falls behind catches up. A malformed
        keyframe is left out and its error returned; the others are added.

        Returns (the estimate to act on, or None when nothing was added and none exists yet;
        [EstimatorError] of the keyframes left out)."""
        errors: list[EstimatorError] = []
        added = 0
        for kf in keyframes:
            try:
                self._add(kf)
                added += 1
            except _OnlineFailed as exc:  # the keyframe is kept
                added += 1
                errors.append(exc)
            except EstimatorError as exc:
                errors.append(exc)
        if added == 0:
            return self._batch, errors
        return self._publish(confirm), errors

    def _add(self, kf: Keyframe) -> None:
        """Validate and keep kf (EstimatorError: nothing kept), then feed the online part. A failure
        of the online part (a bug, a numerical breakdown) must not cost the mission its estimate:
        the online part is dropped, the batch refreshes go on (no confirm from then on), and the
        failure is raised once as an EstimatorError after the keyframe was kept."""
        check_keyframe(kf, self._args[0])
        self._keyframes.append(kf)
        if self._online is None:
            return
        if kf.vehicle != self._keyframes[0].vehicle:
            # the online window links each keyframe to the one before it, which in a fleet is
            # another vehicle's: a fleet is estimated by the batch refreshes alone (whose chains
            # follow each vehicle, estimator.problem)
            self._online = None
            log.info("keyframes of a second vehicle: batch refreshes only from now on")
            return
        try:
            self._online.add_keyframe(kf)
        except Exception as exc:  # any failure of the online part: degrade, report
            self._online = None
            self.online_failure = (f"online estimator failed at keyframe {len(self._keyframes)} "
                                   f"({type(exc).__name__}: {exc}); batch refreshes only from now on")
            log.warning("%s", self.online_failure)
            raise _OnlineFailed(self.online_failure) from exc

    def _publish(self, confirm: Callable[[Estimate], bool] | None) -> Estimate:
        n = len(self._keyframes)
        online = self.online_estimate
        due = self.refresh_due()
        may_confirm = n - self._confirm_at >= CONFIRM_MIN_KEYFRAMES and n > self._batch_at
        if not due and online is not None and confirm is not None and may_confirm and confirm(online):
            self._confirm_at = n
            due = True
        if due:
            est = self.refresh()
            if confirm is not None and not self._batch_exact and confirm(est):
                est = self.refresh(cold=True)
            return est
        if self._batch is not None:
            return self._batch
        if online is None:  # no online part: the first refresh comes early
            return self.refresh()
        return _tagged(online, SOURCE_ONLINE, n)

    def refresh(self, cold: bool = False) -> Estimate:
        """Solve the batch over every keyframe seen now; return (and keep) its estimate. cold: every
        choice made anew from no initial guess, exactly as the final answer (solve_batch of the
        keyframes) is."""
        n_users, up, noise, params = self._args
        n = len(self._keyframes)
        warm = None if cold or self._batch is None or n >= COLD_GROWTH * self._cold_at else self._batch
        init = None if cold or self._batch is None else self._batch.users_enu_m
        est = solve_batch(self._keyframes, n_users, up, noise, params, init_users_enu_m=init, warm=warm)
        # the final answer's computation exactly: no warm start and no initial guess
        self._batch_exact = init is None and warm is None
        if est.state is None or not est.state.warm_started:
            self._cold_at = n
        self._batch = _tagged(est, SOURCE_BATCH, n)
        self._batch_at = n
        self.n_refreshes += 1
        return self._batch


def _tagged(est: Estimate, source: str, n_keyframes: int) -> Estimate:
    return dataclasses.replace(est, source=source, keyframes_used=int(n_keyframes))
