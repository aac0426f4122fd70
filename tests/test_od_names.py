"""CiA 301/402 object indices, COB-IDs and EMCY codes are written by name outside their owners (#32 item 3).

dragd/hardware/cia301.py and cia402.py own the numbers (docs/ARCHITECTURE.md, "Who owns each contract"). Everywhere
else in dragd/ and sim/ an integer literal written in hex that is an object index (1000h-6FFFh: communication,
manufacturer and device profile areas), an EMCY code the owners name, or a COB-ID base is a second owner of that
contract. Decimal literals (5000 ms, 4096 counts) are not looked at: an index is written in hex.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from dragd.hardware import cia301, cia402

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
OWNERS = frozenset({"dragd/hardware/cia301.py", "dragd/hardware/cia402.py"})
# whole files not scanned, each with its reason
SKIPPED: dict[str, str] = {}
# (file, value): why that literal is not a CiA 301/402 number
ALLOWED: dict[tuple[str, int], str] = {
    ("dragd/realtime.py", 0x2000): "MCL_CURRENT on ppc/sparc/alpha (mlockall flags), not an object index",
    ("dragd/realtime.py", 0x4000): "MCL_FUTURE on ppc/sparc/alpha (mlockall flags), not an object index",
}
OD_AREAS = range(0x1000, 0x7000)  # communication (1000h-1FFFh), manufacturer (2000h-5FFFh), profile (6000h-9FFFh)
# COB-ID bases and the 11-bit mask, when written as COB-IDs are (three hex digits: 0x080, not the byte mask 0x80)
COB_IDS = frozenset({cia301.SYNC_COB_ID, cia301.TIME_COB_ID, cia301.TPDO1_BASE, cia301.RPDO1_BASE,
                     cia301.SDO_TX_BASE, cia301.SDO_RX_BASE, cia301.HEARTBEAT_BASE, cia301.COB_ID_MASK})
EMCY_CODES = frozenset(v for k, v in vars(cia402).items() if k.startswith("EMCY_") and isinstance(v, int) and v)


def _hex_literals(text: str, name: str) -> list[tuple[int, int, str]]:
    """(line, value, source text) of every integer literal written in hex."""
    found = []
    lines = text.splitlines()  # (once: ast.get_source_segment splits the whole text again for every literal)
    for node in ast.walk(ast.parse(text, name)):
        if isinstance(node, ast.Constant) and type(node.value) is int and node.end_lineno == node.lineno:
            # the literal's text (one line; the offsets count UTF-8 bytes, as get_source_segment's do)
            src = lines[node.lineno - 1].encode()[node.col_offset:node.end_col_offset].decode()
            if src.lower().startswith("0x"):
                found.append((node.lineno, node.value, src))
    return found


def _what(value: int, src: str) -> str | None:
    if value in OD_AREAS:
        return "an object index (or an EMCY code)"
    if value in EMCY_CODES:
        return "an EMCY code"
    if value in COB_IDS and len(src) == 5:
        return "a COB-ID base (or the COB-ID mask)"
    return None


def test_cia_numbers_are_written_by_name_outside_their_owners() -> None:
    files = sorted(p for root in ("dragd", "sim") for p in (REPO / root).rglob("*.py"))
    assert len(files) > 50, "the scan found too few modules to mean anything"
    found = []
    used: set[tuple[str, int]] = set()
    for path in files:
        rel = path.relative_to(REPO).as_posix()
        if rel in OWNERS or rel in SKIPPED:
            continue
        for line, value, src in _hex_literals(path.read_text(), rel):
            what = _what(value, src)
            if what is None:
                continue
            if (rel, value) in ALLOWED:
                used.add((rel, value))
                continue
            found.append(f"{rel}:{line}: {src} looks like {what}")
    assert not found, ("write these by their name from dragd/hardware/cia301.py or cia402.py (add the name there if "
                       "missing), or allow them in tests/test_od_names.py with the reason:\n" + "\n".join(found))
    stale = sorted(set(ALLOWED) - used)
    assert not stale, f"tests/test_od_names.py allows literals that are gone: {stale}"


def test_the_scan_finds_a_raw_index() -> None:
    """The scan itself: an index, an EMCY code and a COB-ID base in hex are found; decimals and names are not."""
    source = ("from x import OD_CONTROLWORD\na = 0x6040\nb = 0x8130\nc = 0x180 + 1\nd = 6040\ne = OD_CONTROLWORD\n"
              "f = 0x80\n")
    flagged = [(line, _what(v, src)) for line, v, src in _hex_literals(source, "probe") if _what(v, src)]
    assert flagged == [(2, "an object index (or an EMCY code)"), (3, "an EMCY code"),
                       (4, "a COB-ID base (or the COB-ID mask)")]


def test_emcy_codes_have_names_in_their_cia301_class() -> None:
    """Every named EMCY code lies in the CiA 301 class its name says (python-canopen's table, not ours); codes
    without a name are reported by class."""
    from canopen.emcy import EmcyError

    def cia301_class(code: int) -> str:
        return next(text for base, mask, text in EmcyError.DESCRIPTIONS if code & mask == base)

    expected = {cia402.EMCY_NO_ERROR: "Error Reset / No Error", cia402.EMCY_GENERIC: "Generic Error",
                cia402.EMCY_CURRENT: "Current", cia402.EMCY_OVER_CURRENT: "Current",
                cia402.EMCY_TEMPERATURE_DEVICE: "Temperature", cia402.EMCY_COMMUNICATION: "Monitoring",
                cia402.EMCY_HEARTBEAT: "Monitoring", cia402.EMCY_PDO_LENGTH: "Monitoring",
                cia402.EMCY_PDO_LENGTH_EXCEEDED: "Monitoring", cia402.EMCY_RPDO_TIMEOUT: "Monitoring",
                cia402.EMCY_FOLLOWING_ERROR: "Monitoring"}
    assert set(expected) == set(cia402.EMCY_NAMES) == EMCY_CODES | {cia402.EMCY_NO_ERROR}
    assert {code: cia301_class(code) for code in expected} == expected
    assert cia402.emcy_name(cia402.EMCY_HEARTBEAT) == "life guard or heartbeat error"
    assert cia402.emcy_name(0x4310) == "temperature (class)"  # not named: its class
    assert cia402.emcy_name(0xFF42) == "device specific (class)"
    assert cia402.emcy_name(0xA000) == "no CiA 301 class"
