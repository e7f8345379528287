"""Silence refutes a mirror: what the keyframes that did not range a user say (docs/estimator.md).

Ranges from a straight track cannot tell a user at u from its mirror image u' across the track
(estimator.init). A gNB of limited reach R (SolverParams.coverage_m, slant range) hears a UE only
within R, so a keyframe that would have heard the user had it been at h, and did not range it, is
evidence against h. For user k, a hypothesis h (the estimate u or the mirror u'), the other one h̄,
and the N keyframes with GPS fixes x_n at times t_n:

    cell_n     keyframe n's cell could have served k: its vehicle ranged k at some time, and the
               ranges of k nearest in time before and after t_n (where there are any) are that
               vehicle's: k was then no other cell's UE (a fleet's UE is served by one cell at a
               time; with one vehicle every keyframe)
    silent_n   cell_n and k not ranged at keyframe n
    S_h      = #{n : silent_n,  ||x_n − h|| ≤ ρ R,  ||x_n − h̄|| > R}
               silent keyframes that would have heard k at h and could not have at h̄
    q̂        = #{n ∈ B : k ranged at n} / (#B + 1),   B = {n : cell_n, ||x_n − u|| ≤ R, ||x_n − u'|| ≤ R}
               the rate at which k answers a keyframe that has it in reach under either hypothesis
               (near 1 where every keyframe ranges every user in reach, as the fast mode's; lower
               where the gNB's rounds take the users in turn); the + 1 keeps it below 1

    h refuted  ⇔  S_h ≥ SILENT_MIN_KEYFRAMES  and  −2 S_h ln(1 − q̂) ≥ χ²_amb

with ρ = SILENT_REACH_SHARE and χ²_amb = SolverParams.ambiguity_chi2. The second condition is the
likelihood ratio of the silence: at h each of those S_h keyframes misses k with probability 1 − q̂,
at h̄ (out of reach) with probability 1; so the silence costs h −2 S_h ln(1 − q̂) in χ², compared
with the threshold the mirror test compares the ranges' Δχ² with. A keyframe within reach of both
hypotheses misses k alike under both and counts for neither: where the rounds take the users in
turn, the track's own keyframes without k refute nothing. When both hypotheses are refuted the
silence contradicts itself (a reach shorter than R, a UE that stopped answering): neither is.

The fixes x_n, not the solve's track: the margin (1 − ρ) R, tens to hundreds of metres, dwarfs a
fix's error of metres, and the rule is then a function of the data and the two hypotheses alone,
the same in a warm and a cold solve, as the mirror test (also on the fixes) is.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from estimator.problem import Problem

#: silence refutes a hypothesis only with at least this many silent keyframes that would have heard
#: the user there. Where every keyframe ranges every user in reach (q̂ → 1) the likelihood ratio
#: alone would refute on one or two; the floor is for a short run of misses that its independent
#: misses do not model: a gNB that fails some rounds (a mission marks it lost after
#: PROTOCOL_ERROR_STREAK = 3 rounds of nothing but unreadable answers, so up to 2 pass unnoticed),
#: a UE that re-attaches a moment late. 5 keyframes are 8 m of track at Δ = 2 m: the refutation
#: comes a few seconds after the UAV is within ρ R of the phantom, against a survey spent near it.
SILENT_MIN_KEYFRAMES = 5
#: a keyframe "would have heard" a user at h when its fix is within this share of the reach of h:
#: the margin (1 − ρ) R covers the fix's GPS error and the hypothesis's own (metres), and a reach
#: that is softer than R or overstated by up to 1/ρ − 1 = 25 %.
SILENT_REACH_SHARE = 0.8


def cell_rows(prob: Problem, users: Sequence[int], n_rows: int | None = None) -> np.ndarray:
    """(C, n) True where keyframe n's cell could have served user users[c]: its vehicle ranged the
    user at some time, and the user's ranges nearest in time before and after t_n (where there are
    any) are that vehicle's (module docstring: cell_n). One vehicle (prob.vehicle None): all."""
    n = prob.n_keyframes if n_rows is None else n_rows
    out = np.ones((len(users), n), dtype=bool)
    if prob.vehicle is None:
        return out
    v = prob.vehicle[:n]
    t = prob.t_s[:n] if prob.t_s is not None else np.arange(n, dtype=float)
    for c, k in enumerate(users):
        rows = np.flatnonzero(prob.mask[:n, k])
        if rows.size == 0:
            out[c] = False
            continue
        order = np.argsort(t[rows], kind="stable")
        tr, vr = t[rows][order], v[rows][order]
        prev = np.searchsorted(tr, t, side="right") - 1  # the last range at or before t_n
        nxt = np.searchsorted(tr, t, side="left")  # the first at or after t_n
        ok_prev = (prev < 0) | (vr[np.maximum(prev, 0)] == v)
        ok_next = (nxt >= rows.size) | (vr[np.minimum(nxt, rows.size - 1)] == v)
        out[c] = np.isin(v, vr) & ok_prev & ok_next
    return out


def silence_refutes(
    prob: Problem, users: Sequence[int], estimate_enu_m: np.ndarray, mirror_enu_m: np.ndarray,
    n_rows: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Whether silence refutes each user's estimate and its mirror (module docstring), on the first
    n_rows keyframes: users (C,) indices, estimate_enu_m and mirror_enu_m (C, 3) [m, ENU]. Returns
    ((C,) estimate refuted, (C,) mirror refuted), never both; all False with an unlimited reach."""
    c_n = len(users)
    reach = float(prob.params.coverage_m)
    if c_n == 0 or not np.isfinite(reach):
        return np.zeros(c_n, dtype=bool), np.zeros(c_n, dtype=bool)
    n = prob.n_keyframes if n_rows is None else n_rows
    x = prob.gps_enu_m[:n]
    ranged = prob.mask[:n][:, list(users)].T  # (C, n)
    cell = cell_rows(prob, users, n)
    d_u = np.linalg.norm(x[None, :, :] - np.asarray(estimate_enu_m, float)[:, None, :], axis=2)
    d_m = np.linalg.norm(x[None, :, :] - np.asarray(mirror_enu_m, float)[:, None, :], axis=2)
    # q̂: the answer rate where both hypotheses are within reach
    both = cell & (d_u <= reach) & (d_m <= reach)
    q = (both & ranged).sum(axis=1) / (both.sum(axis=1) + 1.0)
    silent = cell & ~ranged
    near = SILENT_REACH_SHARE * reach
    s_u = (silent & (d_u <= near) & (d_m > reach)).sum(axis=1)
    s_m = (silent & (d_m <= near) & (d_u > reach)).sum(axis=1)
    chi2 = float(prob.params.ambiguity_chi2)
    cost = -2.0 * np.log1p(-q)  # χ² a silent keyframe costs the hypothesis that should have heard it

    def refuted(s: np.ndarray) -> np.ndarray:
        return (s >= SILENT_MIN_KEYFRAMES) & (s * cost >= chi2)

    est_ref, mir_ref = refuted(s_u), refuted(s_m)
    both_ref = est_ref & mir_ref
    return est_ref & ~both_ref, mir_ref & ~both_ref
