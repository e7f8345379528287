"""Trace mode on a gNB whose UEs attached before uavloc's T client connected: one PDCCH order each.

A UE that attached before the T client connected has no random access in the trace, so its
absolute timing advance (the RAR's) is unknown (mission.gnb.trace_rtt: `unknown_rntis`). A gNB
patched with patches/oai-2025.w36 serves `rtt pdcch_order <rnti>`: the order makes the UE do a
random access, whose RAR the T trace carries with its absolute TA, and the tracker starts that UE
over from it. :class:`TraceOrders` decides when to order (a UE without an absolute TA, at most
`tries` orders ORDER_SPACING_S apart, never again once the gNB said it has no such command) and
keeps what the mission log's events say (drained by the pipeline).

The order's answer is a round trip too, r_o at t_o. The first trace range r_t of that UE stamped
after the order (at t_t) must agree with it:

    |r_t − r_o| ≤ tol + v_max · (t_t − t_o)      (tol, v_max: the trace's jump_tolerance_m, max_range_rate_mps)

otherwise the UE did not apply the RAR's TA (43 of 1 000 orders in the patch's soak: the UE kept
N_TA = 0 and the trace's TA is a step count too high): the trace's ranges of that UE are withheld
and it is ordered again. Pure: no sockets, no clocks (the caller passes its times).
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: how many orders one UE gets, and how far apart [s] (an order answers within ~0.2 s; its RAR and
#: three agreeing SRS occasions follow within about a second)
ORDER_TRIES = 3
ORDER_SPACING_S = 5.0


@dataclass(frozen=True)
class TraceOrder:
    """One thing an order did. rnti; what: "ordered" (answered with a range), "failed" (an error
    line or no answer), "disagree" (the trace's range after it disagreed with its answer),
    "agree"; range_m: the order's answer [m] (None when it failed); message: the event's text."""

    rnti: int
    what: str
    range_m: float | None
    message: str

    def fields(self) -> dict:
        """The mission log event's fields."""
        return {"rnti": f"{self.rnti:04x}", "order": self.what,
                **({"order_range_m": round(self.range_m, 3)} if self.range_m is not None else {})}


@dataclass
class _Answer:
    range_m: float
    t_s: float


@dataclass
class TraceOrders:
    """See the module docstring. tries, spacing_s: ORDER_TRIES, ORDER_SPACING_S; tolerance_m,
    max_rate_mps: the trace's jump tolerance [m] and fastest range change [m/s]."""

    tolerance_m: float
    max_rate_mps: float
    tries: int = ORDER_TRIES
    spacing_s: float = ORDER_SPACING_S
    #: whether the gNB serves the order (None: not asked yet)
    served: bool | None = None
    _sent: dict[int, list[float]] = field(default_factory=dict)
    _check: dict[int, _Answer] = field(default_factory=dict)
    _redo: set[int] = field(default_factory=set)
    _events: list[TraceOrder] = field(default_factory=list)

    def wanted(self, rnti: int, unknown: bool, now_s: float) -> bool:
        """Order `rnti` now? unknown: the trace has no absolute TA of it (tracker.unknown_rntis)."""
        if self.served is False or not (unknown or rnti in self._redo):
            return False
        sent = self._sent.get(rnti, [])
        return len(sent) < self.tries and (not sent or now_s - sent[-1] >= self.spacing_s)

    def sending(self, rnti: int, now_s: float) -> None:
        self._sent.setdefault(rnti, []).append(now_s)

    def not_served(self, why: str) -> None:
        """The gNB has no order command (a stock gNB): never asked again."""
        self.served = False

    def answered(self, rnti: int, range_m: float, t_s: float) -> None:
        """The order's answer: a range [m] measured at t_s."""
        self.served = True
        self._redo.discard(rnti)
        self._check[rnti] = _Answer(range_m, t_s)
        n = len(self._sent.get(rnti, []))
        self._events.append(TraceOrder(rnti, "ordered", range_m, (
            f"UE {rnti:04x} attached before the T trace began (no absolute TA): a PDCCH order made it do a random "
            f"access, whose RAR the trace takes its TA from (order {n} of {self.tries}, answered {range_m:.2f} m)")))

    def failed(self, rnti: int, why: str) -> None:
        """The order got an error line or no answer: tried again after spacing_s (tries allowing)."""
        n = len(self._sent.get(rnti, []))
        self._events.append(TraceOrder(rnti, "failed", None, (
            f"UE {rnti:04x}: the PDCCH order for its absolute TA failed (order {n} of {self.tries}): {why}")))

    def check(self, rnti: int, range_m: float, t_s: float) -> str | None:
        """A trace range of `rnti` [m] stamped t_s: None when it may be used, else why it is withheld."""
        if rnti in self._redo:
            return f"UE {rnti:04x}: the trace's TA disagreed with the PDCCH order's answer; ordering it again"
        o = self._check.get(rnti)
        if o is None:
            return None
        if t_s <= o.t_s:
            return f"UE {rnti:04x}: the trace's range predates the PDCCH order"
        # |r_t − r_o| ≤ tol + v_max (t_t − t_o)
        allowed = self.tolerance_m + self.max_rate_mps * (t_s - o.t_s)
        del self._check[rnti]
        if abs(range_m - o.range_m) <= allowed:
            self._events.append(TraceOrder(rnti, "agree", o.range_m, (
                f"UE {rnti:04x}: the trace's first range after the PDCCH order, {range_m:.2f} m, agrees with the "
                f"order's {o.range_m:.2f} m")))
            return None
        self._redo.add(rnti)
        why = (f"UE {rnti:04x}: the trace's first range after the PDCCH order, {range_m:.2f} m, is "
               f"{range_m - o.range_m:+.2f} m off the order's {o.range_m:.2f} m (more than {allowed:.2f} m: the UE "
               "did not apply the RAR's TA); its trace ranges are withheld and it is ordered again")
        self._events.append(TraceOrder(rnti, "disagree", o.range_m, why))
        return why

    def status(self, rnti: int) -> str:
        """What the orders did for `rnti`, for a why-no-range message ("" when none was sent)."""
        n = len(self._sent.get(rnti, []))
        if n == 0:
            return "" if self.served is not False else "; the gNB has no PDCCH order command (patches/oai-2025.w36)"
        if rnti in self._check:
            return f"; {n} PDCCH order(s) sent, its RAR awaited in the trace"
        return f"; {n} of {self.tries} PDCCH order(s) sent"

    def drain(self) -> list[TraceOrder]:
        """The events not yet taken, oldest first."""
        out, self._events = self._events, []
        return out
