"""The mission's estimator, defined once: what a flight (`uavloc fly`, `uavloc sim`), replay, the
campaigns (fast and full mode) and the benchmarks estimate with.

- during the flight, the estimate acted on (planner, stop rule, operator) is
  :class:`estimator.refresh.RefreshedEstimator`: the online estimator as the fast inner step,
  refreshed by batch solves on its schedule, and at once when the stop rule holds on the online
  estimate (`confirm`);
- the stop rule: every user's 95 % bound within the target radius (planner.stop.targets_reached),
  judged on a batch estimate only (`stops`);
- the final answer: the batch solution over every keyframe (what `uavloc replay LOG` computes).

:class:`MissionEstimator` carries the settings of all three; build it with :meth:`from_mission`
(a mission file) or directly. Picklable: the flight's estimator child process builds from it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np

from estimator.batch import solve_batch
from estimator.noise import NoiseModel
from estimator.refresh import RefreshedEstimator
from estimator.types import SOURCE_BATCH, Estimate, Keyframe, SolverParams
from planner.stop import targets_reached

#: a mission's batch answers report each user's covariance widened to its delete-a-block
#: jackknife over this many time blocks (SolverParams.jackknife_blocks, estimator.jackknife)
MISSION_JACKKNIFE_BLOCKS = 8


def mission_solver_params(mission) -> SolverParams:
    """The estimator settings of a :class:`mission.config.MissionConfig`: its keyframe spacing Δ and
    range-bias model, the cell's reach `[gnb] coverage_m` (silence refutes a mirror,
    estimator.silence), the covariance widened by the jackknife (MISSION_JACKKNIFE_BLOCKS) and by a
    one-sided NLoS excess's shift (SolverParams.nlos_shift), the solver's defaults otherwise."""
    return SolverParams(delta_m=mission.flight.delta_m, estimate_bias=mission.noise.estimate_bias,
                        bias_prior_sigma_m=mission.noise.bias_prior_sigma_m, bias_held=mission.noise.bias_held,
                        jackknife_blocks=MISSION_JACKKNIFE_BLOCKS, nlos_shift=True,
                        coverage_m=float(mission.gnb.coverage_m))


def solver_params_header(params: SolverParams) -> dict:
    """The solver settings as the log header's `config.solver` holds them, read back by
    mission.replay.solver_params_from_header: every field but an unlimited coverage_m (the log's
    JSON has no infinities), which is left out and reads back as the default, inf."""
    out = asdict(params)
    if not math.isfinite(out["coverage_m"]):
        del out["coverage_m"]
    return out


@dataclass(frozen=True)
class MissionEstimator:
    """The settings of the mission's estimator (module docstring).

    n_users: K; user_up_m: (K,) each user's known height, ENU up [m]; noise: the noise model
    assumed; params: the solver's settings; target_radius_m: the stop rule's radius [m] (None: no
    stop rule, e.g. a replay: no confirm, never stops).
    """

    n_users: int
    user_up_m: np.ndarray
    noise: NoiseModel
    params: SolverParams
    target_radius_m: float | None = None

    @classmethod
    def from_mission(cls, mission, params: SolverParams | None = None,
                     noise: NoiseModel | None = None) -> MissionEstimator:
        """The estimator a mission file flies with (params / noise: replace the mission's)."""
        return cls(len(mission.users), np.array([u.ground_height_m for u in mission.users], float),
                   mission.noise_model() if noise is None else noise,
                   mission_solver_params(mission) if params is None else params,
                   float(mission.flight.target_radius_m))

    def with_noise(self, noise: NoiseModel) -> MissionEstimator:
        return replace(self, noise=noise)

    def estimator(self, online: bool = True) -> RefreshedEstimator:
        """A fresh estimator, fed keyframe by keyframe (online=False: batch refreshes alone, for a
        history computed after the fact)."""
        return RefreshedEstimator(self.n_users, self.user_up_m, self.noise, self.params, online=online)

    @property
    def confirm(self) -> Callable[[Estimate], bool] | None:
        """The predicate on the online estimate that asks for a batch refresh at once: the stop rule
        (picklable); None without one."""
        if self.target_radius_m is None:
            return None
        return functools.partial(targets_reached, target_radius_m=self.target_radius_m)

    def stops(self, estimate: Estimate | None) -> bool:
        """The stop rule on an estimate the mission acts on: a batch estimate with every user's 95 %
        bound within the target radius."""
        return (self.target_radius_m is not None and estimate is not None
                and estimate.source == SOURCE_BATCH and targets_reached(estimate, self.target_radius_m))

    def within_target(self, final: Estimate) -> bool:
        """Whether the final answer bounds every user within the target (no target: False). It
        decides how a survey that stopped at its target or its floor ends: a flight surveys on when
        the target is not held, and a floor the final answer bounds within the target is the target
        reached (mission.control.flight, the campaigns' fast mode)."""
        return self.target_radius_m is not None and targets_reached(final, self.target_radius_m)

    def final(self, keyframes: Sequence[Keyframe]) -> Estimate:
        """The mission's final answer: the batch solution over every keyframe."""
        return solve_batch(list(keyframes), self.n_users, self.user_up_m, self.noise, self.params)
