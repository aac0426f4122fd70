"""Write the EDS variants in this folder from dragd's own ``canopen_eds/joint_drive.eds``.

Each variant is a classic-CAN drive (8 mapping entries per PDO, no ``CANopenFD``) that differs from the bundled
drive in one property seen in a vendor's EDS (docs/DRIVES.md), so CI tests dragd's drive profiles without the
vendors' files (which are never committed):

    classic.eds            the bundled drive on classic CAN: the base of every other variant
    no_dummies.eds         [DummyUsage] all 0 (maxon EPOS4, Technosoft iPOS)
    no_6075h.eds           no 6075h; the rated current in a vendor object 3001h:1 [mA]; 6076h writable, 0 (EPOS4)
    two_rpdos.eds          RPDO 1 and 2 only (Schunk PRL120)
    bit30_cobids.eds       TPDO COB-IDs with bit 30 set ("no RTR"), kept by the drive (Eyou)
    only_6077h.eds         no 6078h: the current from 6077h (per mille of 6076h) (Eyou, simco)
    vendor_current.eds     no 6078h; the current in 30D1h:2, INTEGER32 mA (EPOS4)
    readonly_mapping.eds   TPDO1 and RPDO1 mappings read-only (fixed), the others free
    no_6007h.eds           no 6007h, 605Ah, 6072h (ZeroErr eRob, Eyou)
    no_rpdo_deadline.eds   RPDO communication parameters without sub 5; a vendor watchdog 2F10h [ms] (EPOS4,
                           Eyou, simco)
    tpdo_no_timers.eds     TPDO communication parameters without inhibit time (sub 3) or event timer (sub 5) (simco)
    no_cst.eds             6502h without CST (Technosoft iPOS): refused
    no_6071h.eds           no 6071h; 607Ah not PDO-mappable (Schunk PRL120): refused
    no_60fdh.eds           no 60FDh digital inputs (Eyou EuServo; Wittenstein simco keeps them in 3A13h:5)
    no_60b2h.eds           no 60B2h torque offset: the command is 6071h, which CSP ignores; motions in CST (Eyou)

Run ``python tests/data/eds/make_variants.py`` after changing the bundled EDS; the files are committed.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
SOURCE = HERE.parents[2] / "canopen_eds" / "joint_drive.eds"
CLASSIC_ENTRIES = 8


class Eds:
    """An EDS as ordered sections of ``key=value`` lines (comments and order kept; no reformatting)."""

    def __init__(self, text: str) -> None:
        self.sections: list[tuple[str, list[str]]] = []
        for line in text.splitlines():
            m = re.match(r"^\[(.+)\]\s*$", line)
            if m:
                self.sections.append((m.group(1), []))
            elif self.sections:
                self.sections[-1][1].append(line)

    def text(self) -> str:
        out = []
        for name, lines in self.sections:
            out.append(f"[{name}]")
            body = list(lines)
            while body and not body[-1].strip():
                body.pop()
            out.extend(body)
            out.append("")
        return "\n".join(out)

    def _find(self, name: str) -> list[str]:
        for n, lines in self.sections:
            if n.upper() == name.upper():
                return lines
        raise KeyError(name)

    def get(self, section: str, key: str) -> str | None:
        for line in self._find(section):
            k, _, v = line.partition("=")
            if k.strip() == key:
                return v.strip()
        return None

    def set(self, section: str, key: str, value: str) -> None:
        lines = self._find(section)
        for i, line in enumerate(lines):
            if line.partition("=")[0].strip() == key:
                lines[i] = f"{key}={value}"
                return
        at = len(lines)
        while at > 0 and not lines[at - 1].strip():
            at -= 1
        lines.insert(at, f"{key}={value}")

    def has(self, section: str) -> bool:
        return any(n.upper() == section.upper() for n, _ in self.sections)

    def remove_object(self, index: int) -> None:
        """An object and its sub-indices, and its line in the object lists."""
        head = f"{index:04X}"
        self.sections = [(n, ls) for n, ls in self.sections
                         if not (n.upper() == head or re.fullmatch(rf"{head}SUB[0-9A-F]+", n.upper()))]
        self._relist()

    def remove_sub(self, index: int, sub: int) -> None:
        name = f"{index:04X}sub{sub:X}"
        self.sections = [(n, ls) for n, ls in self.sections if n.upper() != name.upper()]
        subs = [n for n, _ in self.sections if re.fullmatch(rf"{index:04X}SUB[0-9A-F]+", n.upper())]
        self.set(f"{index:04X}", "SubNumber", str(len(subs)))

    def add_object(self, index: int, sections: list[tuple[str, list[str]]], listing: str) -> None:
        """Sections of a new object, placed before the first object with a higher index."""
        pos = len(self.sections)
        for i, (n, _) in enumerate(self.sections):
            m = re.fullmatch(r"([0-9A-F]{4})(SUB[0-9A-F]+)?", n.upper())
            if m and int(m.group(1), 16) > index:
                pos = i
                break
        self.sections[pos:pos] = sections
        lst = self._find(listing)
        count = int(self.get(listing, "SupportedObjects") or "0")
        self.set(listing, "SupportedObjects", str(count + 1))
        lst.insert(len([x for x in lst if x.strip()]), f"{count + 1}=0x{index:04X}")
        self._relist()

    def _relist(self) -> None:
        present = {int(n, 16) for n, _ in self.sections if re.fullmatch(r"[0-9A-Fa-f]{4}", n)}
        for listing in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
            if not self.has(listing):
                continue
            lines = self._find(listing)
            items = [int(line.partition("=")[2], 16) for line in lines
                     if re.match(r"^\d+=", line.strip())]
            items = [i for i in items if i in present]
            lines[:] = [f"SupportedObjects={len(items)}"] + [f"{k}=0x{i:04X}" for k, i in enumerate(items, 1)] + [""]


def var(name: str, access: str, data_type: int, default: str, pdo: int, extra: tuple[str, ...] = ()) -> list[str]:
    return [f"ParameterName={name}", "ObjectType=0x7", f"DataType=0x{data_type:04X}", f"AccessType={access}",
            f"DefaultValue={default}", f"PDOMapping={pdo}", *extra, ""]


def record(index: int, name: str, subs: list[tuple[int, list[str]]]) -> list[tuple[str, list[str]]]:
    top = (f"{index:04X}", [f"ParameterName={name}", "ObjectType=0x9", f"SubNumber={len(subs)}", ""])
    return [top] + [(f"{index:04X}sub{s:X}", lines) for s, lines in subs]


def classic(eds: Eds, product: str, description: str) -> None:
    """The bundled drive as a classic-CAN product: 8 mapping entries per PDO."""
    eds.set("FileInfo", "FileName", f"{product}.eds")
    eds.set("FileInfo", "Description", description)
    eds.set("DeviceInfo", "ProductName", f"dragd EDS variant {product}")
    code = f"0x{0x100 + list(VARIANTS).index(product):08X}"  # each variant its own product code (1018h:2)
    eds.set("DeviceInfo", "ProductNumber", code)
    eds.set("1018sub2", "DefaultValue", code)
    eds.set("DeviceInfo", "CANopenFD", "0")
    for base in (0x1600, 0x1A00):
        for k in range(4):
            index = base + k
            if not eds.has(f"{index:04X}"):
                continue
            for sub in range(CLASSIC_ENTRIES + 1, 0x41):
                eds.remove_sub(index, sub)
            eds.set(f"{index:04X}sub0", "HighLimit", str(CLASSIC_ENTRIES))


def no_dummies(eds: Eds) -> None:
    for i in range(1, 8):
        eds.set("DummyUsage", f"Dummy{i:04d}", "0")


def no_6075h(eds: Eds) -> None:
    eds.remove_object(0x6075)
    eds.set("6076", "AccessType", "rw")  # as EPOS4: 6076h writable, 0 until set
    eds.set("6076", "DefaultValue", "0")
    eds.add_object(0x3001, record(0x3001, "Motor data", [
        (0, var("Highest sub-index supported", "ro", 0x5, "1", 0)),
        (1, var("Nominal current", "rw", 0x7, "1000", 0, ("LowLimit=1",))),
    ]), "ManufacturerObjects")


def two_rpdos(eds: Eds) -> None:
    for index in (0x1402, 0x1403, 0x1602, 0x1603):
        eds.remove_object(index)
    eds.set("DeviceInfo", "NrOfRXPDO", "2")


def bit30_cobids(eds: Eds) -> None:
    for k in range(4):
        eds.set(f"{0x1800 + k:04X}sub1", "DefaultValue", f"$NODEID+0x{0x4000_0180 + 0x100 * k:08X}")


def only_6077h(eds: Eds) -> None:
    eds.remove_object(0x6078)
    _drop_default_mappings(eds, 0x6078)


def vendor_current(eds: Eds) -> None:
    only_6077h(eds)
    eds.add_object(0x30D1, record(0x30D1, "Current actual values", [
        (0, var("Highest sub-index supported", "ro", 0x5, "2", 0)),
        (1, var("Current actual value averaged", "ro", 0x4, "0", 1)),
        (2, var("Current actual value", "ro", 0x4, "0", 1)),
    ]), "ManufacturerObjects")


def readonly_mapping(eds: Eds) -> None:
    """TPDO1 fixed at [6041h, 6064h, 6078h], RPDO1 fixed at [6040h]."""
    for index, words in ((0x1A00, ("0x60410010", "0x60640020", "0x60780010")), (0x1600, ("0x60400010",))):
        eds.set(f"{index:04X}sub0", "AccessType", "ro")
        eds.set(f"{index:04X}sub0", "DefaultValue", str(len(words)))
        for sub in range(1, CLASSIC_ENTRIES + 1):
            eds.set(f"{index:04X}sub{sub:X}", "AccessType", "ro")
            eds.set(f"{index:04X}sub{sub:X}", "DefaultValue", words[sub - 1] if sub <= len(words) else "0x00000000")


def no_6007h(eds: Eds) -> None:
    for index in (0x6007, 0x605A, 0x6072):
        eds.remove_object(index)


def no_rpdo_deadline(eds: Eds) -> None:
    for k in range(4):
        eds.remove_sub(0x1400 + k, 5)
        eds.set(f"{0x1400 + k:04X}sub0", "DefaultValue", "0x02")
    eds.add_object(0x2F10, [("2F10", var("CAN communication watchdog time", "rw", 0x6, "0", 0))],
                   "ManufacturerObjects")


def tpdo_no_timers(eds: Eds) -> None:
    for k in range(4):
        eds.remove_sub(0x1800 + k, 3)
        eds.remove_sub(0x1800 + k, 5)
        eds.set(f"{0x1800 + k:04X}sub0", "DefaultValue", "0x02")


def no_60b2h(eds: Eds) -> None:
    eds.remove_object(0x60B2)
    _drop_default_mappings(eds, 0x60B2)


def no_cst(eds: Eds) -> None:
    eds.set("6502", "DefaultValue", "0x00000080")  # CSP only (bit 7); bit 9 (CST) clear


def no_6071h(eds: Eds) -> None:
    eds.remove_object(0x6071)
    _drop_default_mappings(eds, 0x6071)
    eds.set("607A", "PDOMapping", "0")
    _drop_default_mappings(eds, 0x607A)


def no_60fdh(eds: Eds) -> None:
    eds.remove_object(0x60FD)


def _drop_default_mappings(eds: Eds, index: int) -> None:
    """Default mappings that name a removed or unmappable object are emptied (a drive would not ship them)."""
    for base in (0x1600, 0x1A00):
        for k in range(4):
            m = f"{base + k:04X}"
            if not eds.has(m):
                continue
            count = int(eds.get(f"{m}sub0", "DefaultValue") or "0", 0)
            words = [int(eds.get(f"{m}sub{s:X}", "DefaultValue") or "0", 0) for s in range(1, count + 1)]
            if any(w >> 16 == index for w in words):
                eds.set(f"{m}sub0", "DefaultValue", "0")
                for s in range(1, count + 1):
                    eds.set(f"{m}sub{s:X}", "DefaultValue", "0x00000000")


VARIANTS: dict[str, tuple[str, Callable[[Eds], None] | None]] = {
    "classic": ("the bundled drive on classic CAN (8 mapping entries per PDO)", None),
    "no_dummies": ("no dummy mapping ([DummyUsage] all 0)", no_dummies),
    "no_6075h": ("no 6075h; rated current in vendor object 3001h:1 (mA); 6076h rw, 0", no_6075h),
    "two_rpdos": ("two RPDOs only", two_rpdos),
    "bit30_cobids": ("TPDO COB-IDs keep bit 30 (no RTR)", bit30_cobids),
    "only_6077h": ("no 6078h; current from 6077h (per mille of 6076h)", only_6077h),
    "vendor_current": ("no 6078h; current in vendor object 30D1h:2 (INTEGER32, mA)", vendor_current),
    "readonly_mapping": ("TPDO1 and RPDO1 mappings read-only", readonly_mapping),
    "no_6007h": ("no 6007h, 605Ah, 6072h", no_6007h),
    "no_rpdo_deadline": ("RPDOs without event timer (sub 5); vendor watchdog 2F10h", no_rpdo_deadline),
    "tpdo_no_timers": ("TPDOs without inhibit time and event timer", tpdo_no_timers),
    "no_cst": ("6502h without cyclic synchronous torque", no_cst),
    "no_6071h": ("no 6071h target torque; 607Ah not mappable", no_6071h),
    "no_60fdh": ("no 60FDh digital inputs", no_60fdh),
    "no_60b2h": ("no 60B2h torque offset", no_60b2h),
}


def build(name: str) -> str:
    description, change = VARIANTS[name]
    eds = Eds(SOURCE.read_text(encoding="utf-8"))
    classic(eds, name, f"dragd EDS variant: {description}")
    if change is not None:
        change(eds)
    return eds.text()


def main() -> int:
    for name in VARIANTS:
        (HERE / f"{name}.eds").write_text(build(name), encoding="utf-8")
        print(HERE / f"{name}.eds")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
