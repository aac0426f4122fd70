"""CiA 301 error handling of one simulated node: active errors, error register (1001h), pre-defined error field
(1003h, as many entries as the EDS gives it) and the EMCY producer (1014h).

Objects the EDS lacks are kept internally: 1001h and 603Fh as plain values, 1014h as the pre-defined connection
set's 80h + node-ID, no history without 1003h (docs/SIM_DRIVES.md).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import can

from dragd.hardware.cia301 import (
    COB_ID_MASK,
    EMCY_BASE,
    OD_EMCY_COB_ID,
    OD_ERROR_HISTORY,
    OD_ERROR_REGISTER,
    NmtState,
)
from dragd.hardware.cia402 import EMCY_NO_ERROR, ERR_REG_GENERIC, OD_ERROR_CODE
from sim.od import ABORT_VALUE_RANGE, ObjectStore, SdoAbort

_EMCY = struct.Struct("<HB5s")
_EMCY_PRODUCING = frozenset({NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL})


class Errors:
    """Active error conditions, their register and history, and the EMCY frames they cause."""

    def __init__(self, store: ObjectStore, node_id: int, nmt_state: Callable[[], NmtState],
                 tx: Callable[[can.Message], None], counters: Any) -> None:
        self.store = store
        self.node_id = node_id
        self._nmt_state = nmt_state
        self._tx = tx
        self.counters = counters  # (emcys_sent)
        self.active: dict[int, int] = {}  # error code -> error register bits
        s = store
        self.s_register = s.slot_or_internal(OD_ERROR_REGISTER, 0, "error_register", 0)
        self.s_error_code = s.slot_or_internal(OD_ERROR_CODE, 0, "error_code", 0)
        self.s_emcy_cob = s.slot_or_internal(OD_EMCY_COB_ID, 0, "emcy_cob_id", EMCY_BASE + node_id)
        self.history_size = max((sub for sub in s.subindices(OD_ERROR_HISTORY) if sub > 0), default=0)
        if self.history_size:
            s.before_write[OD_ERROR_HISTORY] = self._check_history_write
            s.after_write[OD_ERROR_HISTORY] = self._clear_history
        s.before_write[OD_EMCY_COB_ID] = self._check_cob

    # --- error conditions --------------------------------------------------------------------------------
    def raise_error(self, code: int, register_bits: int, manufacturer: bytes = b"") -> None:
        """An error condition appears: register, history, EMCY."""
        self.active[code] = register_bits
        self.update_register()
        self._push_history(code, manufacturer)
        self.send(code, manufacturer)

    def note(self, code: int, register_bits: int) -> None:
        """An error condition without an EMCY of its own (a fault whose EMCY went out already)."""
        self.active[code] = register_bits
        self.update_register()

    def clear(self, code: int) -> bool:
        """A non-latched condition went away; EMCY 0000h once none remains. Whether it was active."""
        if code not in self.active:
            return False
        del self.active[code]
        self.update_register()
        if not self.active:
            self.send(EMCY_NO_ERROR, b"")
        return True

    def reset(self) -> None:
        """Fault reset: every condition cleared, 603Fh 0, EMCY 0000h."""
        self.active.clear()
        self.store.cells[self.s_error_code] = 0
        self.update_register()
        self.send(EMCY_NO_ERROR, b"")

    def forget(self) -> None:
        """Power-on: no conditions (the register and history come back with the store's defaults)."""
        self.active.clear()

    def update_register(self) -> None:
        register = 0
        for bits in self.active.values():
            register |= bits | ERR_REG_GENERIC
        self.store.cells[self.s_register] = register

    # --- EMCY producer -------------------------------------------------------------------------------------
    def send(self, code: int, manufacturer: bytes) -> None:
        if self._nmt_state() not in _EMCY_PRODUCING:
            return
        cells = self.store.cells
        cob = cells[self.s_emcy_cob]
        if cob & 0x80000000:
            return
        data = _EMCY.pack(code, cells[self.s_register], manufacturer[:5].ljust(5, b"\x00"))
        self.counters.emcys_sent += 1
        self._tx(can.Message(arbitration_id=cob & COB_ID_MASK, data=data, is_extended_id=False, check=False))

    def _check_cob(self, sub: int, value: int) -> None:
        if value & 0x7FFFF800:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_EMCY_COB_ID, 0, "expected an 11-bit COB-ID (bit 31 = EMCY disabled)")

    # --- pre-defined error field -------------------------------------------------------------------------
    def _push_history(self, code: int, manufacturer: bytes) -> None:
        n = self.history_size
        if not n:
            return
        st = self.store
        extra = int.from_bytes(manufacturer[:2].ljust(2, b"\x00"), "little")
        for sub in range(n, 1, -1):
            st.set(OD_ERROR_HISTORY, sub, st.get(OD_ERROR_HISTORY, sub - 1))
        st.set(OD_ERROR_HISTORY, 1, code | extra << 16)
        st.set(OD_ERROR_HISTORY, 0, min(n, st.get(OD_ERROR_HISTORY, 0) + 1))

    def _check_history_write(self, sub: int, value: int) -> None:
        if sub != 0 or value != 0:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_ERROR_HISTORY, sub, "only 0 may be written to sub-index "
                                                                     "0 (clear history)")

    def _clear_history(self, sub: int, value: int) -> None:
        for s in range(1, self.history_size + 1):
            self.store.set(OD_ERROR_HISTORY, s, 0)
