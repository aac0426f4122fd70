"""CiA 301 SDO server: expedited and segmented upload/download with standard abort codes.

Block transfer is not offered: block requests are answered with abort 0x05040001 (a client may then use
segmented transfer, as CiA 301 allows for servers without block support).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

from sim.od import (
    ABORT_GENERAL,
    ABORT_LENGTH_MISMATCH,
    ABORT_TOGGLE,
    ABORT_UNKNOWN_COMMAND,
    ObjectStore,
    SdoAbort,
)

log = logging.getLogger(__name__)
_HEADER = struct.Struct("<BHB")
_ABORT = struct.Struct("<BHBI")
_SIZE = struct.Struct("<I")

CCS_DOWNLOAD_SEGMENT = 0
CCS_INITIATE_DOWNLOAD = 1
CCS_INITIATE_UPLOAD = 2
CCS_UPLOAD_SEGMENT = 3
CCS_ABORT = 4

_IDLE, _DOWNLOADING, _UPLOADING = 0, 1, 2


class SdoServer:
    """One SDO server channel: request frames in, 8-byte response payloads out through `send`."""

    def __init__(self, store: ObjectStore, send: Callable[[bytes], None]) -> None:
        self.store = store
        self.send = send
        self.requests = 0
        self.aborts_sent = 0
        self.malformed = 0
        self._reset_transfer()

    def _reset_transfer(self) -> None:
        self._mode = _IDLE
        self._index = 0
        self._subindex = 0
        self._toggle = 0
        self._buffer = bytearray()
        self._size: int | None = None

    def reset(self) -> None:
        """Drop any transfer in progress (communication reset)."""
        self._reset_transfer()

    def on_request(self, data: bytes) -> None:
        """Handle one request frame (CiA 301: always 8 data bytes)."""
        if len(data) != 8:
            self.malformed += 1
            return
        self.requests += 1
        ccs = data[0] >> 5
        try:
            if ccs == CCS_INITIATE_DOWNLOAD:
                self._initiate_download(data)
            elif ccs == CCS_DOWNLOAD_SEGMENT:
                self._download_segment(data)
            elif ccs == CCS_INITIATE_UPLOAD:
                self._initiate_upload(data)
            elif ccs == CCS_UPLOAD_SEGMENT:
                self._upload_segment(data)
            elif ccs == CCS_ABORT:
                self._reset_transfer()
            else:
                _, index, subindex = _HEADER.unpack_from(data)
                raise SdoAbort(ABORT_UNKNOWN_COMMAND, index, subindex,
                               f"command specifier {ccs} not supported (block transfer is not offered)")
        except SdoAbort as exc:  # (CiA 301: the abort names the transfer's object, whichever object refused it)
            if ccs in (CCS_INITIATE_DOWNLOAD, CCS_INITIATE_UPLOAD):
                _, index, subindex = _HEADER.unpack_from(data)
            elif ccs in (CCS_DOWNLOAD_SEGMENT, CCS_UPLOAD_SEGMENT) and self._mode != _IDLE:
                index, subindex = self._index, self._subindex
            else:
                index, subindex = exc.index, exc.subindex
            self._abort(exc.code, index, subindex)
        except Exception:  # (a request must never go unanswered: a client would time out and retry)
            log.exception("SDO request %s failed", bytes(data).hex())
            _, index, subindex = _HEADER.unpack_from(data)
            self._abort(ABORT_GENERAL, index, subindex)

    # --- download --------------------------------------------------------------------------------------
    def _initiate_download(self, data: bytes) -> None:
        command, index, subindex = _HEADER.unpack_from(data)
        self._reset_transfer()
        expedited = bool(command & 0x02)
        size_indicated = bool(command & 0x01)
        if expedited:
            n = 4 - ((command >> 2) & 0x3) if size_indicated else 4
            self.store.sdo_write(index, subindex, bytes(data[4:4 + n]), size_known=size_indicated)
        else:
            self.store.check_writable(index, subindex)
            self._mode = _DOWNLOADING
            self._index, self._subindex = index, subindex
            self._size = _SIZE.unpack_from(data, 4)[0] if size_indicated else None
        self.send(_HEADER.pack(0x60, index, subindex) + b"\x00\x00\x00\x00")

    def _download_segment(self, data: bytes) -> None:
        if self._mode != _DOWNLOADING:
            raise SdoAbort(ABORT_UNKNOWN_COMMAND, self._index, self._subindex,
                           "download segment without an initiated segmented download")
        command = data[0]
        toggle = command & 0x10
        if toggle != self._toggle:
            raise SdoAbort(ABORT_TOGGLE, self._index, self._subindex, "toggle bit not alternated")
        unused = (command >> 1) & 0x7
        self._buffer += data[1:8 - unused]
        last = bool(command & 0x01)
        if last:
            index, subindex, buffer, size = self._index, self._subindex, bytes(self._buffer), self._size
            self._reset_transfer()
            if size is not None and size != len(buffer):
                raise SdoAbort(ABORT_LENGTH_MISMATCH, index, subindex,
                               f"received {len(buffer)} bytes, initiate announced {size}")
            self.store.sdo_write(index, subindex, buffer)
        else:
            self._toggle ^= 0x10
        self.send(bytes((0x20 | toggle, 0, 0, 0, 0, 0, 0, 0)))

    # --- upload ----------------------------------------------------------------------------------------
    def _initiate_upload(self, data: bytes) -> None:
        _, index, subindex = _HEADER.unpack_from(data)
        self._reset_transfer()
        value = self.store.sdo_read(index, subindex)
        size = len(value)
        if 0 < size <= 4:
            command = 0x43 | ((4 - size) << 2)
            self.send(_HEADER.pack(command, index, subindex) + value + bytes(4 - size))
            return
        self._mode = _UPLOADING
        self._index, self._subindex = index, subindex
        self._buffer = bytearray(value)
        self.send(_HEADER.pack(0x41, index, subindex) + _SIZE.pack(size))

    def _upload_segment(self, data: bytes) -> None:
        if self._mode != _UPLOADING:
            raise SdoAbort(ABORT_UNKNOWN_COMMAND, self._index, self._subindex,
                           "upload segment without an initiated segmented upload")
        toggle = data[0] & 0x10
        if toggle != self._toggle:
            raise SdoAbort(ABORT_TOGGLE, self._index, self._subindex, "toggle bit not alternated")
        chunk = bytes(self._buffer[:7])
        del self._buffer[:7]
        last = not self._buffer
        command = toggle | ((7 - len(chunk)) << 1) | (0x01 if last else 0)
        if last:
            self._reset_transfer()
        else:
            self._toggle ^= 0x10
        self.send(bytes((command,)) + chunk + bytes(7 - len(chunk)))

    def _abort(self, code: int, index: int, subindex: int) -> None:
        self._reset_transfer()
        self.aborts_sent += 1
        self.send(_ABORT.pack(0x80, index, subindex, code or ABORT_GENERAL))
