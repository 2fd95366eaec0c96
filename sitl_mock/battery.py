"""A LiPo battery that drains with what the vehicle does (idle, armed on the ground, flying)."""

from __future__ import annotations

from dataclasses import dataclass

IDLE_CURRENT_A = 0.5
ARMED_ON_GROUND_CURRENT_A = 2.0
HOVER_CURRENT_A = 15.0
CURRENT_PER_MPS_A = 0.5
CELL_FULL_V = 4.2
CELL_EMPTY_V = 3.5
INTERNAL_RESISTANCE_OHM = 0.01


@dataclass
class Battery:
    """Charge bookkeeping. ``drain`` with the vehicle's state each step."""

    capacity_mah: float
    cells: int = 4
    consumed_mah: float = 0.0
    current_a: float = 0.0

    @property
    def remaining_pct(self) -> float:
        return max(0.0, 100.0 * (1.0 - self.consumed_mah / self.capacity_mah))

    @property
    def voltage_v(self) -> float:
        """Pack voltage: linear from full to empty per cell, with a little sag under load."""
        cell_v = CELL_EMPTY_V + (CELL_FULL_V - CELL_EMPTY_V) * self.remaining_pct / 100.0
        return max(0.0, self.cells * cell_v - INTERNAL_RESISTANCE_OHM * self.current_a)

    def drain(self, dt_s: float, armed: bool, flying: bool, speed_mps: float) -> None:
        """Consume ``dt_s`` seconds' worth of charge (a hover is ~15 A: 250 mAh a minute)."""
        if not armed:
            self.current_a = IDLE_CURRENT_A
        elif not flying:
            self.current_a = ARMED_ON_GROUND_CURRENT_A
        else:
            self.current_a = HOVER_CURRENT_A + CURRENT_PER_MPS_A * speed_mps
        self.consumed_mah += self.current_a * dt_s / 3.6  # A·s -> mAh
