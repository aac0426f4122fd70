"""dragd/hardware/eds.py: an EDS parsed once per file, each node's dictionary derived from it, equals python-canopen's
own ``import_od(path, node_id)`` object by object, attribute by attribute — for every EDS in the repository, the
vendors' files where they are (``$DRAGD_EDS_DIR``), and a file written here with what the others lack (``$NODEID`` in
lower case and with spaces, in a ParameterValue, a [DeviceComissioning] section, compact arrays, [xxxxName] lists).
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path
from typing import Any

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from dragd.hardware import eds

from conftest import REPO

pytestmark = pytest.mark.unit

EDS_DIR = Path(os.environ.get("DRAGD_EDS_DIR", "/work/eds"))
REPO_FILES = sorted([*(REPO / "canopen_eds").glob("*.eds"), *(REPO / "tests" / "data" / "eds").glob("*.eds")])
VENDOR_FILES = sorted(EDS_DIR.glob("*.eds")) if EDS_DIR.is_dir() else []
NODES = (1, 127)  # the template's own node, the highest

EDGE = """\
[FileInfo]
FileName=edge.eds
FileVersion=1
EDSVersion=4.0

[DeviceInfo]
VendorName=dragd tests
VendorNumber=0x1234
ProductName=edge
BaudRate_1000=1
NrOfRXPDO=1
NrOfTXPDO=1

[DeviceComissioning]
NodeID=0x05
Baudrate=1000

[DummyUsage]
Dummy0001=0
Dummy0002=1
Dummy0003=0
Dummy0004=0
Dummy0005=1
Dummy0006=0
Dummy0007=1

[Comments]
Lines=1
Line1=written by tests/test_eds_cache.py

[MandatoryObjects]
SupportedObjects=1
1=0x1000

[OptionalObjects]
SupportedObjects=4
1=0x1014
2=0x1400
3=0x2000
4=0x2100

[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00020192
PDOMapping=0

[1014]
ParameterName=COB-ID EMCY
ObjectType=0x7
DataType=0x0007
AccessType=rw
DefaultValue=$nodeid + 0x80
ParameterValue=0x80 + $NODEID
PDOMapping=0

[1400]
ParameterName=RPDO1 communication parameter
ObjectType=0x9
SubNumber=3

[1400sub0]
ParameterName=Highest sub-index
ObjectType=0x7
DataType=0x0005
AccessType=const
DefaultValue=2
PDOMapping=0

[1400sub1]
ParameterName=COB-ID
ObjectType=0x7
DataType=0x0007
AccessType=rw
DefaultValue=$NODEID+0x200
LowLimit=0x181
HighLimit=0xFFFFFFFF
PDOMapping=0

[1400sub2]
ParameterName=Transmission type
ObjectType=0x7
DataType=0x0005
AccessType=rw
DefaultValue=$NODEID
PDOMapping=0

[2000]
ParameterName=Compact array
ObjectType=0x8
CompactSubObj=3
DataType=0x0004
AccessType=rw
DefaultValue=$NODEID+1
LowLimit=-5
HighLimit=0x7F
PDOMapping=1

[2000Name]
NrOfEntries=2
1=first
2=second

[2100]
ParameterName=Device name
ObjectType=0x7
DataType=0x0009
AccessType=ro
DefaultValue=$NODEID is text here
PDOMapping=0
"""


def _same(a: Any, b: Any, where: str, pairs: dict[int, Any]) -> None:
    """``a`` (canopen's) and ``b`` (ours) hold the same attributes, objects of the same types, parents that
    correspond (``pairs``: canopen's object id -> ours)."""
    assert type(a) is type(b), where
    pairs[id(a)] = b
    assert list(vars(a)) == list(vars(b)), where
    for name, va in vars(a).items():
        vb = vars(b)[name]
        if name == "parent":
            assert (va is None) == (vb is None) and (va is None or pairs[id(va)] is vb), where
        elif name in ("indices", "names", "subindices"):
            assert list(va) == list(vb), f"{where}.{name}"
            for key, obj in va.items():
                _same(obj, vb[key], f"{where}[{key!r}]", pairs)
        elif name == "device_information":
            assert vars(va) == vars(vb), where
        else:
            assert type(va) is type(vb) and va == vb, f"{where}.{name}: {va!r} != {vb!r}"


def _objects(od: canopen.ObjectDictionary) -> dict[int, object]:
    """Every mutable object one dictionary is made of, by id."""
    out: dict[int, object] = {id(od): od, id(od.device_information): od.device_information}
    for obj in od.indices.values():
        members = [obj] if isinstance(obj, ODVariable) else [obj, *obj.subindices.values()]
        for m in members:
            out[id(m)] = m
            for value in vars(m).values():
                if isinstance(value, (dict, set, list)):
                    out[id(value)] = value
    return out


def _check_file(path: Path) -> int:
    """Every node's dictionary equals canopen's; no object is shared between nodes; the number of relative values."""
    ours = {n: eds.import_od(path, n) for n in NODES}
    for n in NODES:
        _same(canopen.import_od(str(path), n), ours[n], f"{path.name} node {n}", {})
    a, b = _objects(ours[NODES[0]]), _objects(ours[NODES[1]])
    assert not set(a) & set(b), f"{path.name}: nodes share objects"
    relative = 0
    for obj in ours[NODES[1]].indices.values():
        members = [obj] if isinstance(obj, ODVariable) else list(obj.subindices.values())
        relative += sum("$NODEID" in (getattr(m, "default_raw", "") or "").upper() for m in members)
    return relative


@pytest.mark.parametrize("path", REPO_FILES, ids=[p.name for p in REPO_FILES])
def test_each_node_equals_canopens_own_import(path: Path) -> None:
    assert _check_file(path) > 0  # the files have COB-IDs relative to the node: the test compares what differs


@pytest.mark.parametrize("name", ["maxon_epos4", "zeroerr_erob", "eyou_euservo", "wittenstein_simco",
                                  "technosoft_ipos", "schunk_prl120"])
def test_each_node_equals_canopens_own_import_on_vendor_files(name: str) -> None:
    path = EDS_DIR / f"{name}.eds"
    if not path.is_file():
        pytest.skip(f"{path} absent (set DRAGD_EDS_DIR to the fetched vendors' EDS files)")
    _check_file(path)


def test_relative_values_text_parameters_and_commissioning(tmp_path: Path) -> None:
    path = tmp_path / "edge.eds"
    path.write_text(textwrap.dedent(EDGE))
    assert _check_file(path) == 6  # 1014h, 1400h:1, 1400h:2, 2000h:1 and its copy 2000h:2, 2100h (text)
    od = eds.import_od(path, 7)
    assert od.node_id == 7 and od.bitrate == 1_000_000
    assert od[0x1014].default == 0x87 and od[0x1014].value == 0x87
    assert od[0x1400][1].default == 0x207
    assert od[0x1400][2].default is None  # canopen cannot convert a bare $NODEID: unset, as in its own import
    assert [od[0x2000][s].default for s in (1, 2)] == [8, 8]
    assert od[0x2100].default == "$NODEID is text here"


def test_cached_per_node_and_file_version(tmp_path: Path) -> None:
    path = tmp_path / "edge.eds"
    path.write_text(textwrap.dedent(EDGE))
    first = eds.import_od(path, 3)
    assert eds.import_od(path, 3) is first and eds.import_od(path, 4) is not first
    path.write_text(textwrap.dedent(EDGE).replace("$nodeid + 0x80", "$NODEID+0x100"))
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1_000_000))
    changed = eds.import_od(path, 3)
    assert changed is not first and changed[0x1014].default == 0x103 and first[0x1014].default == 0x83


def test_a_missing_or_broken_file_raises_what_canopen_raises(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        eds.import_od(tmp_path / "absent.eds", 1)
    (tmp_path / "sub").mkdir()
    broken = tmp_path / "sub" / ".." / "broken.eds"  # the file as the caller names it, in canopen's message too
    broken.write_text("[1000]\nParameterName=x\n[1000]\n")
    with pytest.raises(Exception) as ours:
        eds.import_od(broken, 1)
    with pytest.raises(Exception) as theirs:
        canopen.import_od(str(broken), 1)
    assert type(ours.value) is type(theirs.value) and str(ours.value) == str(theirs.value)
    assert "sub/../broken.eds" in str(ours.value)


def test_objects_are_the_dictionarys_own() -> None:
    """Parents point into the node's own dictionary (a PDO map or an SDO client walks up from a variable)."""
    od = eds.import_od(REPO / "canopen_eds" / "joint_drive.eds", 2)
    for obj in od.indices.values():
        assert obj.parent is od
        if isinstance(obj, (ODRecord, ODArray)):
            assert all(v.parent is obj for v in obj.subindices.values())
