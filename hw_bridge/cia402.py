"""The CiA 402 (IEC 61800-7-201) drive state machine: controlword commands, statusword states.

The simulated robot's drives run :class:`DriveStateMachine`; the bridge reads their
statuswords with :func:`state_of` and commands them with the controlwords below, so both sides
speak the state machine a real drive implements (objects 0x6040 controlword, 0x6041 statusword).
"""

from __future__ import annotations

# controlwords (0x6040), the low byte that selects a transition
SHUTDOWN = 0x06  # -> ready to switch on
SWITCH_ON = 0x07  # -> switched on
ENABLE_OPERATION = 0x0F  # -> operation enabled
DISABLE_VOLTAGE = 0x00  # -> switch on disabled
QUICK_STOP = 0x02  # operation enabled -> quick stop active (the drive stops on its own and holds)
FAULT_RESET = 0x80  # fault -> switch on disabled (rising edge of bit 7)

# states and their statuswords (0x6041, bits 0-3, 5, 6)
NOT_READY = "not ready to switch on"
SWITCH_ON_DISABLED = "switch on disabled"
READY = "ready to switch on"
SWITCHED_ON = "switched on"
OPERATION_ENABLED = "operation enabled"
QUICK_STOP_ACTIVE = "quick stop active"
FAULT_REACTION = "fault reaction active"
FAULT = "fault"
STATUSWORD = {
    NOT_READY: 0x00,
    SWITCH_ON_DISABLED: 0x40,
    READY: 0x21,
    SWITCHED_ON: 0x23,
    OPERATION_ENABLED: 0x27,
    QUICK_STOP_ACTIVE: 0x07,
    FAULT_REACTION: 0x0F,
    FAULT: 0x08,
}
_MASKS = (
    (0x4F, 0x00, NOT_READY),
    (0x4F, 0x40, SWITCH_ON_DISABLED),
    (0x6F, 0x21, READY),
    (0x6F, 0x23, SWITCHED_ON),
    (0x6F, 0x27, OPERATION_ENABLED),
    (0x6F, 0x07, QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, FAULT_REACTION),
    (0x4F, 0x08, FAULT),
)


def state_of(statusword: int) -> str:
    """The state a statusword reports (the standard's bit masks); 'unknown' for anything else."""
    for mask, value, state in _MASKS:
        if statusword & mask == value:
            return state
    return "unknown"


class DriveStateMachine:
    """One drive's device control (drive side): ``command(controlword)`` makes the transition it selects."""

    def __init__(self):
        self.state = SWITCH_ON_DISABLED
        self._reset_bit = False

    @property
    def statusword(self) -> int:
        return STATUSWORD[self.state]

    @property
    def enabled(self) -> bool:
        """Power on the motor and the commanded target applied."""
        return self.state == OPERATION_ENABLED

    def fault(self) -> None:
        """An internal fault (the drive's own watchdog, a limit): the drive stops and reports FAULT."""
        self.state = FAULT

    def command(self, controlword: int) -> str:
        rising = bool(controlword & FAULT_RESET) and not self._reset_bit
        self._reset_bit = bool(controlword & FAULT_RESET)
        low = controlword & 0x0F
        s = self.state
        if s == FAULT:
            if rising:
                self.state = SWITCH_ON_DISABLED
        elif low & 0x02 == 0:  # disable voltage (bit 1 clear), from any powered state
            self.state = SWITCH_ON_DISABLED
        elif low & 0x04 == 0 and s in (READY, SWITCHED_ON, OPERATION_ENABLED):  # quick stop (bit 2 clear)
            self.state = QUICK_STOP_ACTIVE if s == OPERATION_ENABLED else SWITCH_ON_DISABLED
        elif low == SHUTDOWN and s in (SWITCH_ON_DISABLED, SWITCHED_ON, OPERATION_ENABLED):
            self.state = READY
        elif low == SWITCH_ON and s in (READY, OPERATION_ENABLED):
            self.state = SWITCHED_ON
        elif low == ENABLE_OPERATION and s in (READY, SWITCHED_ON, QUICK_STOP_ACTIVE):
            self.state = OPERATION_ENABLED if s != READY else SWITCHED_ON
        return self.state
