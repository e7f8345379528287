"""Several real OAI gNBs, one UE each, as the one gNB a one-vehicle mission talks to.

OAI's no-core mode (`--do-ra`, the only one with SRS without a core network) pre-configures one UE
per gNB, so `uavloc sim --oai` gives each user a gNB + nrUE pair of its own
(docs/oai-in-the-loop.md). :class:`GnbGroup` implements the controller's `GnbClient`
(`mission.gnb.client.GnbClient`: `discover`, `measure`) over their trace-mode adapters: a UE is
measured by the adapter of the gNB it attached to, and discovery lists every gNB's UEs. On the
vehicle the gNBs are one radio (they sit at the same point and follow the same position), which is
what the mission assumes of its one gNB.
"""

from __future__ import annotations

from collections.abc import Sequence

from uavloc.errors import GnbError, GnbNoMeasurementError


class GnbGroup:
    """clients: one entered `OaiGnbClient` per gNB; rntis: the C-RNTI of the UE of each, in order."""

    def __init__(self, clients: Sequence, rntis: Sequence[int]) -> None:
        if len(clients) != len(rntis) or len(set(rntis)) != len(rntis):
            raise GnbError(f"a gNB group needs one distinct RNTI per gNB, got {list(rntis)} for {len(clients)}")
        self.clients = list(clients)
        self.by_rnti = {int(r): c for r, c in zip(rntis, clients, strict=True)}
        #: the adapters measure alike (trace mode); the header's gnb_mode is theirs
        self.mode = self.clients[0].mode
        self.mode_reason = getattr(self.clients[0], "mode_reason", "")

    async def discover(self) -> list[int]:
        """Every gNB's UEs (each gNB lists its own)."""
        out: set[int] = set()
        for c in self.clients:
            out.update(await c.discover())
        return sorted(out)

    async def measure(self, rnti: int):
        """One range of UE `rnti`, by the adapter of its gNB (GnbNoMeasurementError for a UE of none)."""
        client = self.by_rnti.get(rnti)
        if client is None:
            raise GnbNoMeasurementError(f"no gNB of the group serves UE {rnti:04x} (they serve "
                                        f"{', '.join(f'{r:04x}' for r in self.by_rnti)})")
        return await client.measure(rnti)

    def drain_trace_orders(self) -> list:
        """What each adapter's trace-mode PDCCH orders did, not yet taken (mission.gnb.trace_order)."""
        return [o for c in self.clients for o in c.drain_trace_orders()]

    def clock_offset(self):
        """The gNB host's clock offset (the gNBs run on one host: the first adapter's estimate)."""
        return self.clients[0].clock_offset()

    @property
    def clock_refused(self) -> int:
        return sum(int(getattr(c, "clock_refused", 0) or 0) for c in self.clients)

    def trace_gaps(self) -> list:
        """Every adapter's outcomes of a dropped T connection not yet taken (OaiGnbClient.trace_gaps)."""
        return [g for c in self.clients for g in c.trace_gaps()]
