"""SimDevice: the :class:`~falcon_plan.devices.base.Device` contract over the simulated plant.

Each :meth:`~falcon_plan.devices.base.BaseDevice.exchange` advances the
:class:`~falcon_plan.sim.plant.SimPlant` by one control period (the plant applies its own
command delay, quantisation, saturation and effects). ``realtime=True`` sleeps to each tick's
deadline (wall clock); ``realtime=False`` runs as fast as the plant steps. Readings carry the
plant's simulated time.

Paced, by its own deadlines or by a loop's (:meth:`SimDevice.follow_deadlines`), the plant
also lives the slots the loop skipped: an exchange in slot k after one in slot j steps it
k - j periods, the first k - j - 1 under the command in force (as the firmware holds it),
never fewer than one period an exchange. A paced run that misses deadlines then meets what a
real Falcon does (it keeps its own time), not a device that waited for the host. Its logs say
``device_clock: slots``: each row's command acts from its slot, held through the skipped ones.

Homing is immediate: the simulated encoders are zeroed at home already, so :meth:`home` only
marks the legs homed. Buttons always read 0.

If the plant fails (a state outside the reachable workspace, which its end stops normally
prevent), ``exchange`` raises :class:`~falcon_plan.errors.SafetyStop`
naming the cause, and the device stays stopped (further ticks raise
:class:`~falcon_plan.errors.DeviceError`, ``close`` still succeeds) until it is opened again,
which resets a plant the device created (a plant passed in must be reset by its owner).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.devices.base import BaseDevice, DeviceReading
from falcon_plan.errors import DeviceError, SafetyStop, WorkspaceError

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects
    from falcon_plan.sim.plant import SimPlant
    from falcon_plan.timing import DeadlineTimer


class SimDevice(BaseDevice):
    """A simulated Falcon.

    Parameters
    ----------
    plant : SimPlant, optional
        A plant to drive as it is (not reset on open). Default: a new
        ``SimPlant(model, rate_hz=rate_hz, effects=effects, seed=seed)``, reset on open to
        ``start_position_m`` (default: home).
    model, effects, seed
        Passed to the new plant (ignored when ``plant`` is given).
    rate_hz : float
        Loop rate [Hz]; taken from ``plant.rate_hz`` when a plant is given and has one.
    realtime : bool
        Sleep to each tick's deadline (True) or run as fast as possible (False, default).
    start_position_m : array-like, optional
        End-effector position (3,) [m] the new plant starts at on open.
    """

    device_clock = "slots"
    """The plant lives the loop's slots: one period per exchange, and the skipped slots of a
    paced loop under the held command (module docstring)."""
    link_delay_s = 0.0
    """Each reading answers its own command: no link delay beyond the plant's [s]."""

    def __init__(self, plant: "SimPlant | None" = None, *, model: "FalconModel | None" = None,
                 effects: "Effects | None" = None, rate_hz: float = 800.0,
                 realtime: bool = False, start_position_m: Any = None,
                 seed: int | None = None) -> None:
        if plant is None:
            from falcon_plan.sim.plant import SimPlant

            plant = SimPlant(model, rate_hz=rate_hz, effects=effects, seed=seed)
            self._reset_on_open = True
        else:
            rate_hz = float(getattr(plant, "rate_hz", rate_hz))
            self._reset_on_open = False
        super().__init__(rate_hz, realtime)
        self.plant = plant
        """The plant behind the device (its true state is readable for tests)."""
        self._start_position_m = start_position_m
        self._homed = False
        self._counts = np.zeros(3, dtype=np.int64)
        self._fault: str | None = None
        self._deadlines: "DeadlineTimer | None" = None
        self._lived_slot: int | None = None   # the last slot the plant lived, on the deadlines' grid

    @property
    def homed(self) -> bool:
        """True after :meth:`home` (homing is immediate)."""
        return self._homed

    def _connect(self) -> None:
        if self._reset_on_open:
            self.plant.reset(position_m=self._start_position_m)
        self._homed = False
        self._fault = None
        self._lived_slot = None
        self._counts = np.asarray(self.plant.counts, dtype=np.int64).reshape(3).copy()

    def _disconnect(self) -> None:
        """Nothing to release."""

    def _home(self, timeout_s: float) -> None:
        self._homed = True

    def follow_deadlines(self, timer: "DeadlineTimer | None") -> None:
        """``timer``: the deadlines of the loop that exchanges from now on (None: no loop's); while
        it is set, each exchange also lives the slots skipped since the last one (module
        docstring)."""
        self._deadlines = timer
        self._lived_slot = None

    def _periods_due(self) -> int:
        """Control periods the plant lives in this exchange: the slots since the last one on the
        pacing grid (the loop's, else the device's own: the slot its tick runs in), at least
        one; one when unpaced."""
        timer = self._deadlines if self._deadlines is not None else self._timer
        slot = None if timer is None else timer.running_slot
        if slot is None:
            return 1
        if self._lived_slot is None:     # the loop's first exchange
            self._lived_slot = slot
            return 1
        lived = max(self._lived_slot + 1, slot)
        periods, self._lived_slot = lived - self._lived_slot, lived
        return periods

    def _emergency_zero(self) -> None:
        """Nothing to send at once: the simulated plant applies a command only when stepped,
        and the tick in progress (or close()) steps it next."""

    def _transfer(self, commands: np.ndarray, flags: int) -> DeviceReading:
        if self._fault is not None:
            raise DeviceError(f"the simulated device is stopped ({self._fault}); close it and "
                              "open it again (a plant passed in must be reset first)")
        try:
            for _ in range(self._periods_due() - 1):
                self.plant.step(None)          # a skipped slot: the command in force is held
            counts = self.plant.step(commands)
        except WorkspaceError as exc:
            self._fault = "the plant left the reachable workspace"
            raise SafetyStop(f"the simulated device left the reachable workspace: {exc}") from exc
        self._counts = np.asarray(counts, dtype=np.int64).reshape(3)
        homed = (self._homed,) * 3
        return DeviceReading(self._counts, 0, homed, float(self.plant.time_s))
