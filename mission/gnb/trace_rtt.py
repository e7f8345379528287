"""Each UE's round trip, rebuilt from a stock OAI gNB's T-tracer events (pure; no I/O, no clocks).

The gNB never prints a UE's round trip, but its T tracer carries what rebuilds it to the sample
(`../shared/data/oai-2025.w36-ttrace/README.md`, docs/oai.md):

    RTT [samples] = S · (TA_RAR + Σ_applied (TA_cmd − 31)) + (SRS peak − N/2),   S = TA step · fs
                                                                                 (N_FFT/128: 12 at μ=1)

- the RAR's TA is the UE's absolute timing advance at its random access, **if the UE applied
  it**: OAI's nrUE sometimes misses the slot it should apply it in (seen after a PDCCH order,
  tests/data/oai-2025.w36-rtt/orders_7_11_15) and keeps N_TA = 0, and then its SRS peak is the
  whole round trip. The RAR's TA is the round trip rounded or floored (OAI has done both; the
  simulated gNB floors) to TA steps, so an applied TA leaves a peak in [−S/2, S); the first valid
  SRS after a RAR of TA_RAR ≥ 2 with a peak in [S·(TA_RAR − `_RAR_TOL_STEPS`), S·(TA_RAR + 1))
  means not applied (TA 0 from there; an SRS within `RAR_SETTLE_FRAMES` of the RAR is held: the
  UE applies the TA from its Msg3 on). With TA_RAR = 1 the two cannot be told apart (a floored
  RAR TA leaves a peak up to S) and the TA is taken as applied: one TA step too far if it was not;
- a Timing Advance Command MAC CE (every 100 frames; 31 = no change) moves it, **but only if the
  UE applied it**: OAI's UE drops a command that arrives after it prepared the target slot and the
  gNB re-sends it 100 frames later. An applied command shows in the trace itself: the SRS peak
  steps by −S·(TA − 31) within a few SRS occasions. So a command stays *pending* until the peak
  either makes that step (applied) or does not within `resolve_occasions` SRS (dropped); no RTT
  comes out while one is pending;
- the SRS peak carries what the TA loop leaves uncorrected (its dead band is ±S/2);
- OAI traces the SRS estimate also when no SRS was received (a stale buffer): a peak less than
  `min_peak_to_mean_db` above the mean tap power is not an SRS;
- a round trip that grows faster than a vehicle can fly (`max_range_rate_mps`) is not a range: a
  level reached by a jump up (an rfsim distance set on one side only, a UE re-synchronizing) is
  reported only once it has held long enough for that change to be physical. A drop up to
  `clock_step_m` is taken at once: a commercial UE corrects its clock in steps, so its round
  trip rises slowly and then drops (docs/design.md §4); holding the drops would keep only the
  sawtooth's upper part.
- a dropped T connection (:meth:`TraceRttTracker.connection_gap`) hides the TA commands sent
  meanwhile. At each UE's first valid SRS after it, the missed steps k are found from continuity:
  the round trip cannot have moved more than B = tolerance + v_max·Δt since the UE's last valid
  SRS before the gap (Δt: the larger of its air and wall time), so k is the one integer with
  |S·k + p₁ − p₀| ≤ B < S − |S·k + p₁ − p₀| (p₀, p₁: the peaks before and after). Without such
  a k (a gap too long for the peak to tell) the UE's absolute TA is unknown: no RTT until its next
  random access. Each outcome is a :class:`GapOutcome`. Time here is the gNB's air
  time (its frame counter), not the wall clock (an rfsimulator runs faster or slower than real
  time).

:class:`TraceRttTracker` takes decoded events in order (:mod:`mission.gnb.ttrace`) and keeps, per
RNTI, the latest accepted :class:`TraceRtt`; counters say what it refused and why.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

from estimator.ranging import one_way_m_per_sample, ta_step_s
from mission.config import GnbSettings
from mission.gnb.ttrace import (
    EV_DL_PDU,
    EV_DL_RETX,
    EV_PRACH,
    EV_RAR,
    EV_SRS_CHEST,
    EV_SRS_TOA_NS,
    TA_CMD_NO_CHANGE,
    TEvent,
    rar_grants,
    srs_peak,
    ta_commands,
)
from uavloc.errors import GnbProtocolError

#: RNTIs that are not a UE's (SI-RNTI, P-RNTI: SIB1 and paging PDUs)
_NOT_UE_RNTIS = frozenset({0xFFFF, 0xFFFE})
#: how to re-attach a UE that attached before the T client connected (OAI 2025.w36, rfsim:
#: ../shared/data/oai-2025.w36-ttrace, runs sa_no_core and dora_jump_0_300_reattach)
REATTACH_HINT = ("re-attach it while uavloc's T client is connected: `ciUE force_RRC_IDLE` on the nrUE's telnet "
                 "server (the UE re-attaches in SA; in --do-ra mode it exits instead), or restart the nrUE")
#: SFN period [frames]; frames are 10 ms
SFN_PERIOD = 1024
#: frames after a RAR before an SRS shows whether its TA took effect (the UE applies it from its
#: Msg3 slot on, a few slots after the RAR)
RAR_SETTLE_FRAMES = 2
#: how far below S·TA_RAR the first SRS peak after a RAR may be and still mean not applied [TA steps]
_RAR_TOL_STEPS = 0.6
FRAME_S = 0.01
#: a wall-clock step between events after which the frame count is unwrapped by rfsim's pace [s]
PACE_GAP_S = 1.0
#: the wall time over which rfsim's pace is measured [s]
PACE_WINDOW_S = 2.0


#: the thresholds' one definition: a mission file's [gnb] defaults (mission.config.GnbSettings),
#: which `uavloc import --t-trace` and the live trace mode both read
_GNB = GnbSettings()


@dataclass(frozen=True)
class TraceSettings:
    """How the tracker reads the trace: the thresholds of `[gnb]` (mission.config.GnbSettings, one
    definition for `uavloc import --t-trace` and the live trace mode; :meth:`of` makes them from a
    mission's settings) and the tracker's own counts.

    mu, fs_hz: the gNB's numerology and sampling rate (`-E`: 46.08 Msps at 106 PRB, μ = 1);
    min_peak_to_mean_db: an SRS estimate whose peak stands less above the mean tap power is stale
    (real ~31 dB, stale ~9 dB in OAI 2025.w36's rfsim); max_range_rate_mps: the fastest a range may
    change (vehicle plus user speed) [m/s]; jump_tolerance_m: what quantization and peak jitter may
    add to that [m of range]; clock_step_m: the largest drop taken at once (a UE clock correction)
    [m of range]; resolve_occasions: SRS occasions after a TA command within which its step must
    show, else it was dropped; confirm_occasions: SRS occasions that must agree before a UE's first
    RTT (after its random access) is reported; max_rntis: UEs kept (the oldest forgotten first).
    """

    mu: int = _GNB.mu
    fs_hz: float = _GNB.fs_hz
    min_peak_to_mean_db: float = _GNB.srs_min_peak_to_mean_db
    max_range_rate_mps: float = _GNB.trace_max_range_rate_mps
    jump_tolerance_m: float = _GNB.trace_jump_tolerance_m
    clock_step_m: float = _GNB.trace_clock_step_m
    resolve_occasions: int = 3
    confirm_occasions: int = 3
    max_rntis: int = 256

    @classmethod
    def of(cls, gnb: GnbSettings) -> TraceSettings:
        """The tracker's settings from a mission file's (or the adapter's) `[gnb]`."""
        return cls(mu=gnb.mu, fs_hz=gnb.fs_hz, min_peak_to_mean_db=gnb.srs_min_peak_to_mean_db,
                   max_range_rate_mps=gnb.trace_max_range_rate_mps, jump_tolerance_m=gnb.trace_jump_tolerance_m,
                   clock_step_m=gnb.trace_clock_step_m)

    @property
    def rate_tolerance_samples(self) -> float:
        """jump_tolerance_m in RTT samples: m / (c / 2 fs) (1.54 for 5 m at 46.08 Msps)."""
        return self.jump_tolerance_m / one_way_m_per_sample(self.fs_hz)

    @property
    def clock_step_samples(self) -> float:
        """clock_step_m in RTT samples (4.61 for 15 m at 46.08 Msps)."""
        return self.clock_step_m / one_way_m_per_sample(self.fs_hz)

    @property
    def step_samples(self) -> float:
        """RTT samples of one TA step: S = 16·64·Tc/2^μ · fs (12 at μ = 1, 46.08 Msps)."""
        return ta_step_s(self.mu) * self.fs_hz

    @property
    def n_fft(self) -> int:
        """FFT size: fs / (15 kHz · 2^μ) (1536 at 46.08 Msps, μ = 1)."""
        return round(self.fs_hz / (15e3 * 2**self.mu))

    @property
    def rate_samples_per_s(self) -> float:
        """How fast an RTT may move [samples/s]: v_max over the one-way metres of a sample, 2 · v_max · fs / c."""
        return self.max_range_rate_mps / one_way_m_per_sample(self.fs_hz)


@dataclass(frozen=True)
class TraceRtt:
    """One UE's round trip from the trace.

    rnti; ta: the UE's cumulative timing advance [TA steps] (RAR plus applied commands); peak: the
    SRS peak's delay from zero [samples at fs] (fractional); rtt_samples: S·ta + peak; frame, slot:
    the SRS occasion; t_wall_s: when the gNB traced it (its CLOCK_REALTIME) [s]; t_air_s: the gNB's
    air time (unwrapped frame counter) [s]; peak_to_mean_db: the SRS peak's prominence [dB]."""

    rnti: int
    ta: int
    peak: float
    rtt_samples: float
    frame: int
    slot: int
    t_wall_s: float
    t_air_s: float
    peak_to_mean_db: float


@dataclass(frozen=True)
class GapOutcome:
    """What a UE's first valid SRS after a dropped T connection proved (module docstring).

    rnti; proven: the TA is known again (TA += missed_steps) or else unknown until a new access;
    missed_steps: k [TA steps] (0: no command was missed; unproven: the nearest, not taken); gap_s:
    Δt since the UE's last valid SRS before the gap [s]; budget_samples: B; moved_samples:
    S·k + p₁ − p₀ [RTT samples]; message: one sentence for the mission log."""

    rnti: int
    proven: bool
    missed_steps: int
    gap_s: float
    budget_samples: float
    moved_samples: float
    message: str

    def fields(self) -> dict:
        """The event record's fields."""
        return {"rnti": f"{self.rnti:04x}", "proven": self.proven,
                "missed_steps": self.missed_steps if self.proven else None,
                "gap_s": round(self.gap_s, 3), "budget_samples": round(self.budget_samples, 2),
                "moved_samples": round(self.moved_samples, 2)}


@dataclass
class _Pending:
    cmd: int
    seen: int = 0  # valid SRS occasions since it was sent


@dataclass
class _Ue:
    ta: int
    pending: _Pending | None = None  # the TA command not yet seen applied or dropped (the gNB sends one at a time)
    ref_peak: float | None = None  # the latest valid peak
    ref_air_s: float = 0.0  # ... its air time [s]
    ref_wall_s: float = 0.0  # ... its gNB wall stamp [s]
    gap: bool = False  # a T connection dropped since ref_peak: the next valid SRS checks the TA
    lost: str = ""  # why the absolute TA is unknown (until the next random access)
    streak: list[float] = field(default_factory=list)  # RTTs of the first occasions, to confirm
    accepted: TraceRtt | None = None
    held: str = ""  # why the latest valid occasion gave no RTT
    rar_t_air_s: float | None = None  # air time of the RAR whose TA's effect no SRS has shown yet


@dataclass
class TraceCounts:
    """What the tracker has seen since it started (the probe prints them)."""

    events: int = 0
    rars: int = 0
    prach: int = 0
    ta_commands: int = 0
    ta_applied: int = 0
    ta_dropped: int = 0
    rar_ta_not_applied: int = 0
    srs: int = 0
    srs_stale: int = 0
    srs_unknown_ue: int = 0
    rtts: int = 0
    held_pending: int = 0
    held_rate: int = 0
    malformed: int = 0
    last_malformed: str = ""
    gaps: int = 0
    gap_proven: int = 0
    gap_lost: int = 0


class TraceRttTracker:
    """Follows every RNTI's timing advance and SRS residual in a stream of T events.

    feed(event) -> the TraceRtt the event produced (or None); latest(rnti) -> the newest accepted
    TraceRtt of that UE; ues() -> the RNTIs it knows (random access seen); counts: TraceCounts.
    A malformed event is counted and skipped (the tracker never raises on data).
    """

    def __init__(self, settings: TraceSettings | None = None) -> None:
        self.settings = settings if settings is not None else TraceSettings()
        self._ues: collections.OrderedDict[int, _Ue] = collections.OrderedDict()
        self._last_frame: int | None = None
        self._last_wall_s: float | None = None
        self._air_frames = 0
        self._pace_ref: tuple[float, float] | None = None  # (air, wall) [s] where the pace window began
        #: rfsim's pace: the gNB's air seconds per wall second (None before PACE_WINDOW_S of events)
        self.pace: float | None = None
        self.counts = TraceCounts()
        #: RNTIs whose SRS or TA came without a random access seen (attached before the trace began)
        self.unknown_rntis: set[int] = set()
        #: what each UE's first valid SRS after a dropped connection proved, not yet taken (drain_gaps)
        self.gap_outcomes: collections.deque[GapOutcome] = collections.deque(maxlen=256)

    # -- time ---------------------------------------------------------------------------------
    def _air_s(self, frame: int, slot: int, t_wall_s: float) -> float:
        """The gNB's air time [s] from its frame counter, unwrapped.

        Events of one gNB arrive in frame order give or take a few frames (MAC and PHY trace from
        different threads): the nearest unwrapping, d ∈ (−512, 512] frames. After a wall-clock
        step of more than PACE_GAP_S (a dropped T connection) d is the one nearest what rfsim's pace
        (air seconds per wall second, measured over PACE_WINDOW_S) predicts. A wall-clock gap longer
        than half an SFN period makes the unwrapping ambiguous: every UE's rate reference restarts."""
        f = int(frame) % SFN_PERIOD
        d = 0
        gap = False
        if self._last_frame is not None and self._last_wall_s is not None:
            dw = t_wall_s - self._last_wall_s
            d = (f - self._last_frame) % SFN_PERIOD
            if abs(dw) > 5.0:
                # a gap: keep air time monotonic, and trust no earlier level or streak
                d, gap = 2 * SFN_PERIOD, True
                for ue in self._ues.values():
                    ue.streak.clear()
                    ue.accepted = None
            elif dw > PACE_GAP_S and self.pace is not None:
                predicted = dw * self.pace / FRAME_S
                d += SFN_PERIOD * round((predicted - d) / SFN_PERIOD)
            elif d > SFN_PERIOD // 2:
                d -= SFN_PERIOD
        self._air_frames += d
        self._last_frame = f
        self._last_wall_s = t_wall_s
        slot_s = 1e-3 / 2**self.settings.mu
        air_s = self._air_frames * FRAME_S + int(slot) * slot_s
        ref = self._pace_ref
        if gap or ref is None:
            self._pace_ref = (air_s, t_wall_s)
        elif t_wall_s - ref[1] >= PACE_WINDOW_S:
            self.pace = (air_s - ref[0]) / (t_wall_s - ref[1])
            self._pace_ref = (air_s, t_wall_s)
        return air_s

    def connection_gap(self) -> None:
        """The T connection dropped and is back: events (TA commands among them) were missed. Each
        known UE's TA is checked at its next valid SRS (module docstring); until then a pending
        command's fate is unknown (the check covers it) and no RTT comes out."""
        self.counts.gaps += 1
        for ue in self._ues.values():
            if ue.lost:
                continue
            ue.gap = True
            ue.pending = None
            ue.streak.clear()
            ue.held = "a T connection dropped: its TA is checked at its next SRS"

    def drain_gaps(self) -> list[GapOutcome]:
        """The gap outcomes not yet taken, oldest first."""
        out = list(self.gap_outcomes)
        self.gap_outcomes.clear()
        return out

    def _check_gap(self, rnti: int, ue: _Ue, peak: float, t_air_s: float, t_wall_s: float) -> None:
        """The first valid SRS after a gap: k from continuity, or the TA unknown."""
        s = self.settings
        ue.gap = False
        step = s.step_samples
        if ue.ref_peak is None:
            k, moved, gap_s, budget = 0, math.nan, math.nan, math.nan
            proven = False
            why = "no valid SRS of it before the gap to compare with"
        else:
            gap_s = max(t_air_s - ue.ref_air_s, t_wall_s - ue.ref_wall_s, 0.0)
            budget = s.rate_tolerance_samples + s.rate_samples_per_s * gap_s
            k = round((ue.ref_peak - peak) / step)
            moved = step * k + peak - ue.ref_peak
            proven = abs(moved) <= budget < step - abs(moved)
            why = (f"in {gap_s:.2f} s its round trip may have moved ±{budget:.1f} samples, and TA steps are "
                   f"{step:g}: the SRS peak ({ue.ref_peak:+.2f} -> {peak:+.2f}) cannot tell how many were missed")
        if proven:
            ue.ta += k
            self.counts.gap_proven += 1
            what = ("no TA command was missed" if k == 0 else
                    f"{k:+d} TA step(s) were applied while it was not seen: TA {ue.ta - k} -> {ue.ta}")
            msg = (f"UE {rnti:04x} after the T connection dropped: {what} (its round trip moved {moved:+.2f} "
                   f"samples in {gap_s:.2f} s, within ±{budget:.1f}; a missed step would be {step:g})")
        else:
            ue.lost = why
            ue.accepted = None
            self.counts.gap_lost += 1
            msg = (f"UE {rnti:04x} after the T connection dropped: its absolute TA is unknown ({why}); no range "
                   "from it until it re-attaches")
        self.gap_outcomes.append(GapOutcome(rnti, proven, int(k), float(gap_s), float(budget), float(moved), msg))

    # -- events ---------------------------------------------------------------------------------
    def feed(self, ev: TEvent) -> TraceRtt | None:
        """Take one event (in the order the gNB sent them); the RTT it produced, if any."""
        self.counts.events += 1
        try:
            if ev.name == EV_SRS_CHEST:
                return self._srs(ev, *self._chest_peak(ev))
            if ev.name == EV_SRS_TOA_NS:
                return self._srs(ev, *self._toa_ns_peak(ev))
            if ev.name in (EV_DL_PDU, EV_DL_RETX):
                self._dl_pdu(ev)
            elif ev.name == EV_RAR:
                self._rar(ev)
            elif ev.name == EV_PRACH:
                self.counts.prach += 1
        except (GnbProtocolError, KeyError, TypeError, ValueError) as exc:
            self.counts.malformed += 1
            self.counts.last_malformed = f"{ev.name}: {exc}"
        return None

    def _rar(self, ev: TEvent) -> None:
        v = ev.values
        t_air = self._air_s(int(v["frame"]), int(v["slot"]), ev.t_wall_s)  # keeps the frame count unwrapped
        for g in rar_grants(bytes(v["data"])):
            self.counts.rars += 1
            # a fresh access: its RAR TA is absolute; whatever this RNTI had before is history
            self._ues.pop(g.tc_rnti, None)
            self._ues[g.tc_rnti] = _Ue(ta=g.ta, rar_t_air_s=t_air)
            self.unknown_rntis.discard(g.tc_rnti)
            while len(self._ues) > self.settings.max_rntis:
                self._ues.popitem(last=False)

    def _dl_pdu(self, ev: TEvent) -> None:
        v = ev.values
        rnti = int(v["rnti"])
        if rnti in _NOT_UE_RNTIS:
            return
        cmds = ta_commands(bytes(v["data"]))
        if not cmds:
            return
        self._air_s(int(v["frame"]), int(v["slot"]), ev.t_wall_s)  # every event keeps the frame count unwrapped
        ue = self._ues.get(rnti)
        for cmd in cmds:
            self.counts.ta_commands += 1
            if ue is None:
                self.unknown_rntis.add(rnti)
                continue
            if cmd == TA_CMD_NO_CHANGE:
                continue
            # a re-sent command means the gNB still saw the offset: the older one was dropped
            if ue.pending is not None:
                self.counts.ta_dropped += 1
            ue.pending = _Pending(cmd)

    def _chest_peak(self, ev: TEvent) -> tuple[float, float]:
        """(peak [samples at fs], peak-to-mean [dB]) of an SRS impulse response; taps beyond N_FFT
        are the oversampling of newer OAI branches."""
        p = srs_peak(bytes(ev.values["chest_t"]))
        osf = max(1, round(p.n / self.settings.n_fft))
        return p.peak / osf, p.peak_to_mean_db

    def _toa_ns_peak(self, ev: TEvent) -> tuple[float, float]:
        """GNB_PHY_UL_SRS_TOA_NS (newer OAI): int16 ns per receive antenna, antenna 0 taken;
        −32768 marks an invalid estimate (as OAI's SRS indication does)."""
        raw = bytes(ev.values[next(k for k in ev.values if k not in ("gNB_ID", "rnti", "frame", "slot"))])
        ns = int.from_bytes(raw[:2], "little", signed=True)
        if ns == -32768:
            return 0.0, -math.inf
        return ns * 1e-9 * self.settings.fs_hz, math.inf

    def _srs(self, ev: TEvent, peak: float, ratio_db: float) -> TraceRtt | None:
        s = self.settings
        v = ev.values
        rnti = int(v["rnti"])
        frame = int(v["frame"])
        slot = int(v.get("slot", v.get("subframe", 0)))
        t_air = self._air_s(frame, slot, ev.t_wall_s)
        self.counts.srs += 1
        ue = self._ues.get(rnti)
        if ue is None:
            self.counts.srs_unknown_ue += 1
            self.unknown_rntis.add(rnti)
            return None
        if not ratio_db >= s.min_peak_to_mean_db:
            self.counts.srs_stale += 1
            ue.held = f"stale SRS estimate (peak {ratio_db:.1f} dB over the mean)"
            return None
        if ue.gap:
            self._check_gap(rnti, ue, peak, t_air, ev.t_wall_s)
        if ue.lost:
            ue.held = f"its absolute TA is unknown since the T connection dropped ({ue.lost}): {REATTACH_HINT}"
            return None
        if ue.rar_t_air_s is not None and not self._rar_taken(ue, peak, t_air):
            return None
        self._resolve(ue, peak)
        ue.ref_peak, ue.ref_air_s, ue.ref_wall_s = peak, t_air, ev.t_wall_s
        if ue.pending is not None:
            self.counts.held_pending += 1
            ue.held = f"TA command {ue.pending.cmd} not yet seen applied or dropped"
            ue.streak.clear()
            return None
        rtt = s.step_samples * ue.ta + peak
        if rtt < 0.0:
            if rtt <= -0.5:  # more than the peak's own rounding: not a round trip
                ue.held = f"a negative round trip ({rtt:.2f} samples: TA {ue.ta}, peak {peak:+.2f})"
                return None
            peak, rtt = -s.step_samples * ue.ta, 0.0  # a zero distance, within the peak's rounding
        cand = TraceRtt(rnti, ue.ta, peak, rtt, frame, slot, ev.t_wall_s, t_air, ratio_db)
        if ue.accepted is None:
            # the first RTT after an access (or a gap): confirm_occasions that agree
            ue.streak.append(rtt)
            if len(ue.streak) < s.confirm_occasions:
                ue.held = f"confirming the first RTT ({len(ue.streak)} of {s.confirm_occasions} occasions)"
                return None
            recent = ue.streak[-s.confirm_occasions:]
            if max(recent) - min(recent) > s.rate_tolerance_samples:
                ue.held = "the first RTTs disagree"
                return None
            ue.streak.clear()
        else:
            # a level reached faster than anything can fly is held until that change is physical
            ref = ue.accepted
            # |Δ| ≤ tol + rate·Δt, plus clock_step for a drop
            jump = rtt - ref.rtt_samples
            allowed = s.rate_tolerance_samples + s.rate_samples_per_s * max(0.0, t_air - ref.t_air_s)
            if jump < 0:
                allowed += s.clock_step_samples
            if abs(jump) > allowed:
                self.counts.held_rate += 1
                ue.held = (f"RTT moved {jump:+.1f} samples in {t_air - ref.t_air_s:.2f} s of air "
                           f"time, faster than {s.max_range_rate_mps:g} m/s")
                return None
        ue.accepted = cand
        ue.held = ""
        self.counts.rtts += 1
        return cand

    def _rar_taken(self, ue: _Ue, peak: float, t_air: float) -> bool:
        """Whether the UE's TA is known after its RAR, from the first valid SRS peak after it (module
        docstring): True once decided (ue.ta 0 when the UE did not apply the RAR's TA), False while
        an SRS too soon after the RAR looks not applied (held)."""
        s = self.settings
        if ue.ta >= 2 and s.step_samples * (ue.ta - _RAR_TOL_STEPS) <= peak < s.step_samples * (ue.ta + 1):
            if t_air - ue.rar_t_air_s < RAR_SETTLE_FRAMES * FRAME_S:
                ue.held = "SRS before the RAR's TA took effect"
                return False
            self.counts.rar_ta_not_applied += 1
            ue.ta = 0
        ue.rar_t_air_s = None
        return True

    def _resolve(self, ue: _Ue, peak: float) -> None:
        """Decide the pending TA command against this valid SRS peak.

        Applied when the peak is nearer ref − S·(TA − 31) than ref (ref: the peak before), dropped
        after resolve_occasions occasions without that step."""
        p = ue.pending
        if p is None or ue.ref_peak is None:
            return
        step = self.settings.step_samples * (p.cmd - TA_CMD_NO_CHANGE)
        applied_at = ue.ref_peak - step
        if abs(peak - applied_at) < abs(peak - ue.ref_peak):
            ue.ta += p.cmd - TA_CMD_NO_CHANGE
            self.counts.ta_applied += 1
            ue.pending = None
            return
        p.seen += 1
        if p.seen >= self.settings.resolve_occasions:
            self.counts.ta_dropped += 1
            ue.pending = None

    # -- queries -------------------------------------------------------------------------------
    def latest(self, rnti: int) -> TraceRtt | None:
        ue = self._ues.get(rnti)
        return None if ue is None else ue.accepted

    def why_none(self, rnti: int, reattach: str = REATTACH_HINT, where: str = "the T trace") -> str:
        """Why this UE has no RTT now: what the latest of its occasions was held for. reattach:
        what to do about a UE that attached before the trace began; where: what the trace is."""
        ue = self._ues.get(rnti)
        if ue is None:
            if rnti in self.unknown_rntis:
                return (f"UE {rnti:04x} attached before {where} began: its random access (the RAR's absolute "
                        f"TA) was not seen, so its round trip is unknown; {reattach}")
            return f"UE {rnti:04x} has made no random access and sent no SRS in {where}"
        return ue.held or f"UE {rnti:04x} has sent no SRS since its random access"

    def without_absolute_ta(self, rnti: int) -> bool:
        """The trace has no absolute TA of this UE: it attached before the trace began, or a T
        connection gap made its TA unknown (an ordered random access gives it again)."""
        ue = self._ues.get(rnti)
        return rnti in self.unknown_rntis if ue is None else bool(ue.lost)

    def ues(self) -> list[int]:
        return list(self._ues)
