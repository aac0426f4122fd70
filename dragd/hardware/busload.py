"""Worst-case CAN / CAN FD bus load from a PDO layout.

Bit counts per frame (data frames, no error/overload frames, no retransmissions):

Classical CAN (ISO 11898-1), base 11-bit id, ``n`` data bytes::

    47 + 8n + floor((34 + 8n - 1) / 4)       -> 135 bits for n = 8, 55 for n = 0 (SYNC)

47 = SOF 1 + id 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + CRC 15 + CRC delim 1 + ACK 2 + EOF 7
+ IFS 3; the 34 + 8n bits from SOF to the end of the CRC are subject to stuffing,
worst case one stuff bit per 4 bits after the first 5. Extended (29-bit) ids add
SRR 1 + id 18 + r1 1 = 20 stuffable bits.

CAN FD (ISO 11898-1:2015, "ISO CRC"): dynamic stuffing from SOF to the end of the data
field (same worst case), then the CRC field = stuff count (3 Gray bits + parity) and
CRC-17 (n <= 16) or CRC-21 (n > 16), with a fixed stuff bit before it and after every
4th bit (6 fixed stuff bits with CRC-17, 7 with CRC-21). With BRS the data phase runs
at the data bit rate; here the data phase is ESI .. CRC delimiter and the arbitration
phase is SOF .. BRS plus ACK .. IFS (dynamic stuff bits inserted before the BRS bit
count as nominal). The payload is rounded up to the next valid FD length
(0..8, 12, 16, 20, 24, 32, 48, 64).

``stuffing="none"`` gives the lower bound (no stuff bits) so a report can show the
band a real bus falls into.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

__all__ = [
    "FD_LENGTHS",
    "FrameSpec",
    "FrameLoad",
    "BusLoadReport",
    "frame_bits",
    "fd_length",
    "bus_load",
]

Stuffing = Literal["worst", "none"]

FD_LENGTHS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def fd_length(data_bytes: int) -> int:
    """Smallest valid CAN FD payload length >= ``data_bytes``."""
    if data_bytes < 0 or data_bytes > 64:
        raise ValueError(f"CAN FD carries 0..64 data bytes; got {data_bytes}")
    return FD_LENGTHS[bisect.bisect_left(FD_LENGTHS, data_bytes)]


def _dynamic_stuff(stuffable_bits: int) -> int:
    """Worst-case dynamic stuff bits over a span: 1 after 5 equal bits, then 1 per 4."""
    return (stuffable_bits - 1) // 4 if stuffable_bits > 0 else 0


def frame_bits(
    data_bytes: int,
    *,
    fd: bool = False,
    brs: bool = False,
    extended_id: bool = False,
    stuffing: Stuffing = "worst",
) -> tuple[int, int]:
    """Bits of one data frame incl. 3-bit intermission: ``(nominal_bits, data_bits)``.

    ``data_bits`` are the bits sent at the data bit rate (non-zero only for CAN FD
    with ``brs``); everything else is ``nominal_bits``.
    """
    if stuffing not in ("worst", "none"):
        raise ValueError(f"stuffing must be 'worst' or 'none'; got {stuffing!r}")
    worst = stuffing == "worst"
    if not fd:
        if brs:
            raise ValueError("brs=True needs fd=True (bit rate switching exists only in CAN FD)")
        if not 0 <= data_bytes <= 8:
            raise ValueError(
                f"classical CAN carries 0..8 data bytes; got {data_bytes} (use fd=True for more)"
            )
        id_bits = 11 + 20 * extended_id  # extended: + SRR, IDE-after-id, 18 id bits, r1
        stuffable = 1 + id_bits + 1 + 1 + 1 + 4 + 8 * data_bytes + 15  # SOF..CRC
        fixed_tail = 1 + 2 + 7 + 3  # CRC delim, ACK slot+delim, EOF, IFS
        total = stuffable + fixed_tail + (_dynamic_stuff(stuffable) if worst else 0)
        return total, 0

    n = fd_length(data_bytes)
    # Arbitration part up to and including BRS: SOF, id, RRS, IDE, FDF, res, BRS
    # (extended: SOF, id11, SRR, IDE, id18, RRS, FDF, res, BRS).
    arb = 1 + 11 + 1 + 1 + 1 + 1 + 1 + (18 + 1) * extended_id
    ctrl_data = 1 + 4 + 8 * n  # ESI, DLC, data
    dyn_total = _dynamic_stuff(arb + ctrl_data) if worst else 0
    # stuff bit k (k >= 1) follows original bit 4k + 1; it is in the arbitration phase
    # when that bit precedes BRS.
    dyn_arb = min(dyn_total, (arb - 2) // 4) if worst else 0
    crc_len = 17 if n <= 16 else 21
    crc_field = 4 + crc_len  # stuff count (3 + parity) + CRC sequence
    fixed_stuff = 1 + (crc_field - 1) // 4
    data_phase = ctrl_data + (dyn_total - dyn_arb) + crc_field + fixed_stuff + 1  # + CRC delim
    arb_phase = arb + dyn_arb + 1 + 1 + 7 + 3  # + ACK slot, ACK delim, EOF, IFS
    if brs:
        return arb_phase, data_phase
    return arb_phase + data_phase, 0


@dataclass(frozen=True)
class FrameSpec:
    """One periodic frame type on the bus (``count`` identical frames, e.g. one per node)."""

    name: str
    data_bytes: int
    rate_Hz: float
    fd: bool = False
    brs: bool = False
    extended_id: bool = False
    count: int = 1

    def __post_init__(self) -> None:
        if not (self.rate_Hz >= 0 and math.isfinite(self.rate_Hz)):
            raise ValueError(f"frame {self.name!r}: rate_Hz must be >= 0; got {self.rate_Hz!r}")
        if self.count < 1:
            raise ValueError(f"frame {self.name!r}: count must be >= 1; got {self.count!r}")


@dataclass(frozen=True)
class FrameLoad:
    """Per-frame-type line of a `BusLoadReport` (worst case and no-stuffing bound)."""

    spec: FrameSpec
    payload_bytes: int
    nominal_bits: int
    data_bits: int
    nominal_bits_min: int
    data_bits_min: int
    frame_time_us: float
    frames_per_s: float
    bits_per_s: float
    percent: float
    percent_min: float


@dataclass(frozen=True)
class BusLoadReport:
    """Bus load of a frame set: ``percent`` is the worst case, ``percent_min`` without stuffing."""

    bitrate: int
    data_bitrate: int | None
    frames: tuple[FrameLoad, ...]
    percent: float
    percent_min: float
    bits_per_s: float
    frames_per_s: float
    notes: tuple[str, ...] = field(default=())

    @property
    def overloaded(self) -> bool:
        """True when the worst case exceeds 100 % (frames cannot all be sent in time)."""
        return self.percent > 100.0

    def table(self) -> str:
        """Human-readable table with the numbers behind the percentages."""
        rate = f"{self.bitrate / 1e6:g} Mbit/s"
        if self.data_bitrate:
            rate += f", data phase {self.data_bitrate / 1e6:g} Mbit/s"
        head = (
            f"{'frame':<14}{'n':>3}{'bytes':>6}{'type':>7}{'rate Hz':>9}"
            f"{'nom bits':>9}{'data bits':>10}{'us/frame':>9}{'bit/s':>11}{'load %':>8}{'min %':>8}"
        )
        lines = [f"worst-case bus load at {rate}", head, "-" * len(head)]
        for f in self.frames:
            s = f.spec
            kind = ("FD+BRS" if s.brs else "FD") if s.fd else "CAN"
            if s.extended_id:
                kind += "x"
            lines.append(
                f"{s.name:<14.14}{s.count:>3}{f.payload_bytes:>6}{kind:>7}{s.rate_Hz:>9g}"
                f"{f.nominal_bits:>9}{f.data_bits:>10}{f.frame_time_us:>9.2f}"
                f"{f.bits_per_s:>11.0f}{f.percent:>8.2f}{f.percent_min:>8.2f}"
            )
        lines.append("-" * len(head))
        verdict = "OVERLOADED" if self.overloaded else "ok"
        lines.append(
            f"{'total':<14}{'':>3}{'':>6}{'':>7}{'':>9}{'':>9}{'':>10}{'':>9}"
            f"{self.bits_per_s:>11.0f}{self.percent:>8.2f}{self.percent_min:>8.2f}  {verdict}"
        )
        lines.append(
            f"worst case {self.percent:.1f} % (all stuff bits), lower bound "
            f"{self.percent_min:.1f} % (no stuff bits), {self.frames_per_s:g} frames/s"
        )
        lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)


def bus_load(
    frames: Iterable[FrameSpec], bitrate: int, data_bitrate: int | None = None
) -> BusLoadReport:
    """Bus load of periodic ``frames`` at ``bitrate`` (and ``data_bitrate`` for FD+BRS)."""
    if bitrate <= 0:
        raise ValueError(f"bitrate must be a positive bit/s value; got {bitrate!r}")
    if data_bitrate is not None and data_bitrate < bitrate:
        raise ValueError(
            f"data_bitrate ({data_bitrate}) must be >= the nominal bitrate ({bitrate})"
        )
    rows: list[FrameLoad] = []
    notes: list[str] = []
    for s in frames:
        if s.brs and data_bitrate is None:
            raise ValueError(
                f"frame {s.name!r} uses bit rate switching (brs=True) but no data_bitrate was given"
            )
        dbr = data_bitrate or bitrate
        nom, dat = frame_bits(s.data_bytes, fd=s.fd, brs=s.brs, extended_id=s.extended_id)
        nom0, dat0 = frame_bits(
            s.data_bytes, fd=s.fd, brs=s.brs, extended_id=s.extended_id, stuffing="none"
        )
        payload = fd_length(s.data_bytes) if s.fd else s.data_bytes
        if payload != s.data_bytes:
            notes.append(f"{s.name}: {s.data_bytes} bytes padded to the FD length {payload}")
        t = nom / bitrate + dat / dbr
        t0 = nom0 / bitrate + dat0 / dbr
        fps = s.rate_Hz * s.count
        rows.append(
            FrameLoad(
                spec=s,
                payload_bytes=payload,
                nominal_bits=nom,
                data_bits=dat,
                nominal_bits_min=nom0,
                data_bits_min=dat0,
                frame_time_us=t * 1e6,
                frames_per_s=fps,
                bits_per_s=fps * (nom + dat),
                percent=100.0 * fps * t,
                percent_min=100.0 * fps * t0,
            )
        )
    return BusLoadReport(
        bitrate=bitrate,
        data_bitrate=data_bitrate,
        frames=tuple(rows),
        percent=sum(r.percent for r in rows),
        percent_min=sum(r.percent_min for r in rows),
        bits_per_s=sum(r.bits_per_s for r in rows),
        frames_per_s=sum(r.frames_per_s for r in rows),
        notes=tuple(notes),
    )
