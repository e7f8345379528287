"""A fleet's simulated gNBs over one cell attachment (docs/fleet.md, "Whose user is it").

Each vehicle of a simulated fleet carries its own gNB, and a UE is served by one of them at a time,
as :class:`sitl_scenarios.radio.CellAttachment` decides (the model the fast mode uses).
:class:`SharedCells` holds that one attachment, a callable giving every vehicle's true position,
which gNBs are on the air, and each UE's RNTI; a :class:`GnbCell` (the shared cells and a gNB's
index) is what one `SimulatedGnb` is given. Every query of a gNB updates the attachment from the
vehicles' positions at that moment, so the gNBs of a fleet agree on whose UE is whose whichever of
them is asked.

Simplification: a UE keeps its RNTI across cells (one list shared by every gNB of the fleet); OAI
would give it a new one at each attach (a fresh TC-RNTI that becomes its C-RNTI), which the mission
could not follow without reading every gNB's log. The random access of an attach is still logged
(sitl_scenarios.gnb.server.SimulatedGnb) with the UE's RNTI as its TC-RNTI.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sitl_scenarios.radio import CellAttachment
from sitl_scenarios.scenario import Scenario
from uavloc.errors import SimulatorError

#: every vehicle's true position, (V, 3) ENU of the scenario's frame [m]; None: not known yet
PositionsSource = Callable[[], "np.ndarray | Sequence[Sequence[float]] | None"]


class SharedCells:
    """One :class:`CellAttachment` shared by the gNBs of a fleet.

    attachment: whose UE is whose; positions: every gNB's (vehicle's) true position, (V, 3) ENU [m]
    of the attachment's frame, None while unknown (the attachment then stays as it is), a row with a
    NaN: that gNB is not heard; n_cells: V; rntis: (K,) each UE's RNTI, shared by the gNBs (a gNB
    that gives a UE a new one, at a reestablishment, gives it for the fleet).
    on_air: (V,) bool, a gNB that stopped (killed, crashed) is False and its UEs attach elsewhere.
    first_serving: (K,) the serving cells of the first update (the UEs attached when the fleet
    came on the air: their attach is not logged, as a single gNB logs none for the UEs it starts with).
    """

    def __init__(self, attachment: CellAttachment, positions: PositionsSource, n_cells: int,
                 rntis: Sequence[int]) -> None:
        if isinstance(n_cells, bool) or not isinstance(n_cells, int) or n_cells < 1:
            raise SimulatorError(f"n_cells must be a positive integer, got {n_cells!r}")
        if len(rntis) != len(attachment.serving):
            raise SimulatorError(f"{len(rntis)} RNTIs for the {len(attachment.serving)} UEs of the attachment")
        self.attachment = attachment
        self.positions = positions
        self.n_cells = n_cells
        self.on_air = np.ones(n_cells, dtype=bool)
        self.current_rnti: list[int] = [int(r) for r in rntis]
        self.first_serving: np.ndarray | None = None

    @classmethod
    def of_scenario(cls, scenario: Scenario, positions: PositionsSource, n_cells: int | None = None) -> SharedCells:
        """The scenario's UEs (true positions, RNTIs) and cell reach (`[radio] coverage_m`) for
        n_cells gNBs (default: the mission's fleet size); positions in the scenario's ENU frame."""
        users = np.array([[u.east_m, u.north_m, u.up_m] for u in scenario.users], float).reshape(-1, 3)
        n = scenario.mission.fleet_size if n_cells is None else n_cells
        return cls(CellAttachment(users, scenario.radio.coverage_m), positions, n, [u.rnti for u in scenario.users])

    def cell(self, index: int) -> GnbCell:
        """gNB `index`'s (0..n_cells−1) view of the shared cells."""
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < self.n_cells:
            raise SimulatorError(f"cell index must be 0..{self.n_cells - 1}, got {index!r}")
        return GnbCell(self, index)

    def update(self) -> np.ndarray:
        """Attach and detach UEs for the gNBs where `positions` puts them now; (K,) serving cells (−1: none)."""
        pos = self.positions()
        if pos is None:
            return self.attachment.serving.copy()
        g = np.asarray(pos, dtype=float)
        if g.shape != (self.n_cells, 3):
            raise SimulatorError(f"positions gave shape {g.shape}, expected ({self.n_cells}, 3)")
        known = np.all(np.isfinite(g), axis=1)
        serving = self.attachment.update(np.where(known[:, None], g, 0.0), self.on_air & known)
        if self.first_serving is None:
            self.first_serving = serving.copy()
        return serving


@dataclass(frozen=True)
class GnbCell:
    """One gNB's cell among `shared` (its index there): what `SimulatedGnb(cell=...)` serves."""

    shared: SharedCells
    index: int

    def served(self) -> dict[int, int]:
        """{UE index: its attach number (CellAttachment.attaches)} of the UEs attached to this cell
        now (updating the attachment first)."""
        serving = self.shared.update()
        attaches = self.shared.attachment.attaches
        return {k: int(attaches[k]) for k in np.flatnonzero(serving == self.index).tolist()}

    def attached_at_start(self, k: int) -> bool:
        """Whether UE k's present attach to this cell is the one it had when the fleet came on the air."""
        first = self.shared.first_serving
        return first is not None and int(first[k]) == self.index and int(self.shared.attachment.attaches[k]) == 1

    def leave_air(self) -> None:
        """This gNB stops transmitting: its UEs attach elsewhere at the next update."""
        self.shared.on_air[self.index] = False
