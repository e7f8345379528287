"""The random-access lines an OAI 2025.w36 gNB writes to its log, for the simulated gNB.

Texts as in `tests/fixtures/oai-2025.w36/20_gnb_log_ra_lines.txt` (OAI's nr_prach_procedures.c,
gNB_scheduler_RA.c, gNB_scheduler_ulsch.c, rrc_gNB.c, rrc_gNB_UE_context.c), each line with a
`wall_clock` stamp (UNIX seconds) in front. Every access starts with the L1 PRACH line (preamble,
delay = TA), the MAC line with the fresh temporary RNTI and the Msg2 line; what follows tells
whose access it was.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Container
from pathlib import Path

from mission.gnb.oai import format_msg2_line


class OaiRaLog:
    """Appends OAI random-access lines to a gNB log file (nothing when path is None).

    path: the log; wall: UNIX time [s] for the stamps; rng: draws TC-RNTIs and preambles.
    """

    def __init__(self, path: Path | None, wall: Callable[[], float], rng: random.Random) -> None:
        self.path = path
        self.wall = wall
        self.rng = rng
        self.ue_id = 0

    def new_tc_rnti(self, taken: Container[int]) -> int:
        """A random temporary RNTI not in `taken` (OAI draws them at random)."""
        while True:
            r = self.rng.randrange(1, 0xFFF0)
            if r not in taken:
                return r

    def _write(self, lines: list[str]) -> None:
        if self.path is None:
            return
        stamp = f"{self.wall():.6f} "
        with self.path.open("a", encoding="utf-8") as fh:
            fh.write("".join(stamp + ln + "\n" for ln in lines))

    def _access(self, frame: int, tc: int, ta: int, mu: int) -> list[str]:
        preamble = self.rng.randrange(64)
        return [f"[NR_PHY] A [RAPROC] {frame}.19 Initiating RA procedure with preamble {preamble}, energy 44.5 dB "
                f"(I0 0, thres 200), delay {ta} start symbol 8 freq index 0",
                f"[NR_MAC] A {frame}.19 UE RA-RNTI 010b TC-RNTI {tc:04x}: initiating RA procedure",
                format_msg2_line(tc, frame + 1, 10, 0x10B, preamble, ta, mu)]

    def connected(self, frame: int, old: int, tc: int, mu: int) -> None:
        """A connected UE's C-RNTI random access: timing_offset 0 (its TA is already applied)."""
        self._write([*self._access(frame, tc, 0, mu),
                     f"[NR_MAC] A Received a MAC CE for C-RNTI with {old:04x}",
                     f"[NR_MAC] I Received UL_SCH_LCID_C_RNTI with C-RNTI 0x{old:04x}, triggering RRC "
                     f"Reconfiguration",
                     f"[NR_MAC] A  {frame + 1}.19 RA with C-RNTI {old:04x} complete"])

    def initial(self, frame: int, tc: int, ta: int, mu: int) -> None:
        """An initial access: a new UE whose RNTI is the TC-RNTI, full round-trip TA."""
        self.ue_id += 1
        n = self.ue_id
        self._write([*self._access(frame, tc, ta, mu),
                     f"[NR_RRC] A [--] (cellID 0, UE ID {n} RNTI {tc:04x}) Create UE context: CU UE ID {n} DU UE ID "
                     f"{tc} (rnti: {tc:04x}, random ue id {self.rng.getrandbits(60):x})",
                     f"[NR_RRC] A [UL] (cellID bc614e, UE ID {n} RNTI {tc:04x}) Received RRCSetupComplete "
                     f"(RRC_CONNECTED reached)"])

    def reestablishment(self, frame: int, old: int, tc: int, ta: int, mu: int) -> None:
        """The UE `old` reestablishes as `tc`: full round-trip TA, and the line that ties them."""
        self._write([*self._access(frame, tc, ta, mu),
                     f"[NR_RRC] I Reestablishment RNTI {tc:04x} req C-RNTI {old:04x} physCellId 0 cause otherFailure",
                     f"[NR_RRC] A Send RRCReestablishment [34 bytes] to RNTI {tc:04x}"])
