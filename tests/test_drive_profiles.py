"""Drive profiles (#27): each joint's drive from its EDS, checked offline, booted against drives built from the same
EDS by python-canopen (``LocalNode``, tests/eds_nodes.py) on a virtual bus.

The EDS variants in tests/data/eds reproduce, one each, what vendors' EDS files do (tests/data/eds/make_variants.py);
the vendors' files themselves are never committed: the tests on them take ``$DRAGD_EDS_DIR`` (default /work/eds) and
skip without them.

All in one process, no clock of the arm (unit tier): the boots talk SDO to the drives' ``LocalNode`` on a virtual bus,
with an SDO timeout far beyond any host stall (``SDO_GUARD_S``), so a busy machine cannot decide a verdict; the
0.5 s waits of the boot meet drives that answer in the same SDO exchange (or never: the sticky statusword).
"""

from __future__ import annotations

import asyncio
import copy
import functools
import itertools
import os
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from eds_nodes import EdsBus, EdsNode, mapping

from dragd.config import Config
from dragd.hardware.master import DriveError, Master
from dragd.hardware.plan import plan_drives

from conftest import DEFAULT_CONFIG, REPO, run_cli

VARIANTS = REPO / "tests" / "data" / "eds"
SDO_GUARD_S = 5.0  # the boots' SDO timeout here (default 0.3 s): an answer lost in a loaded host's stall is no verdict
EDS_DIR = Path(os.environ.get("DRAGD_EDS_DIR", "/work/eds"))
_channels = itertools.count()


@functools.cache
def _default_config() -> dict[str, Any]:
    """config/default.yaml's data, read once (``config`` works on a deep copy)."""
    data: dict[str, Any] = yaml.safe_load(DEFAULT_CONFIG.read_text())
    return data


def config(eds: Path | None, drive: dict[str, Any] | None = None, *, joints: int = 6, layout: str = "per_node",
           fd: bool = False, targets: bool = True, rate_Hz: float = 250.0) -> Config:
    """config/default.yaml's joints on one bus with ``eds`` (None: dragd's own drive) and profile overrides."""
    data: dict[str, Any] = copy.deepcopy(_default_config())
    data["joints"] = data["joints"][:joints]
    for key, value in data["replay"].items():
        if isinstance(value, list):
            data["replay"][key] = value[:joints]
    data["buses"] = [{"name": "arm", "interface": "virtual", "channel": "x", "fd": fd,
                      **({"data_bitrate": 5_000_000} if fd else {}), "layout": layout, "position_targets": targets}]
    if eds is not None:
        data["drives"] = {"d": {"eds": str(eds), **(drive or {})}}
        for j in data["joints"]:
            j["drive"] = "d"
    data["loop"] = {"rate_Hz": rate_Hz}
    return Config.model_validate({**data, "source": str(REPO / "config" / "test.yaml")})


def facts(cfg: Config, joint: int) -> dict[tuple[int, int], int]:
    """What a drive holds that its EDS gives no value for: the joint's rated current and torque where the profile
    reads them, identity and modes where the EDS leaves them out."""
    from dragd.hardware.profile import CURRENT_UNITS_A, TORQUE_UNITS_NM, DriveProfile, parse_address

    p = DriveProfile(cfg, joint)
    j = cfg.joints[joint]
    out: dict[tuple[int, int], int] = {}
    for index, sub, value in ((0x1000, 0, 0x00020192), (0x1018, 1, 0x1234), (0x1018, 2, 0x42), (0x1018, 3, 1),
                              (0x1018, 4, 7), (0x6502, 0, 0x000003A5)):
        var = p.var(index, sub)
        if var is not None and var.default is None:
            out[(index, sub)] = value
    if p.drive.rated_current.object is not None:
        index, sub = parse_address(p.drive.rated_current.object)
        if p.has(index, sub):
            out[(index, sub)] = round(j.rated_current_A / CURRENT_UNITS_A[p.drive.rated_current.unit])
    rt = p.drive.rated_torque
    if rt.object is not None and not rt.write:
        index, sub = parse_address(rt.object)
        if p.has(index, sub):
            out[(index, sub)] = round(j.rated_torque_motor_Nm / TORQUE_UNITS_NM[rt.unit])
    return out


def boot(cfg: Config, drive_eds: list[Path] | None = None, node_facts: dict[int, dict] | None = None,
         sticky: dict[int, int] | None = None) -> tuple[Master, EdsBus, str | None, list[str]]:
    """Boot ``cfg``'s drives (Master.boot) against EdsNodes from ``drive_eds`` (default: each joint's configured
    EDS); (master, bus, the DriveError text or None, the log)."""
    cfg = cfg.model_copy(update={"master": cfg.master.model_copy(update={"sdo_timeout_s": SDO_GUARD_S})})
    plan = plan_drives(cfg, budget_findings=False)
    assert not plan.errors, "\n".join(f.text for f in plan.errors)
    channel = f"eds-{os.getpid()}-{next(_channels)}"
    nodes = []
    for i, j in enumerate(cfg.joints):
        eds = drive_eds[i] if drive_eds else cfg.eds_of(i)
        f = facts(cfg, i)
        f.update((node_facts or {}).get(j.node_id, {}))
        nodes.append(EdsNode(j.node_id, eds, f, sticky_statusword=(sticky or {}).get(j.node_id)))
    drives = EdsBus(channel, nodes)
    log: list[str] = []

    async def run() -> str | None:
        bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        m = Master(cfg, {"arm": bus}, plan.layouts, asyncio.get_running_loop(), plan.profiles, {}, log=log.append)
        run.master = m  # type: ignore[attr-defined]
        try:
            await m.boot()
            return None
        except DriveError as exc:
            return str(exc)
        finally:
            await m.shutdown()
            bus.shutdown()

    try:
        error = asyncio.run(run())
    finally:
        drives.close()
    return run.master, drives, error, log  # type: ignore[attr-defined]


def check_configured(master: Master, drives: EdsBus) -> None:
    """Every drive holds the layout's mappings, COB-IDs valid, CST selected, controlword 0."""
    for rt in master.runtimes.values():
        for node_id, pdos in rt.layout.pdos.items():
            node = drives.nodes[node_id]
            for pdo in pdos:
                assert mapping(node, pdo.map_index) == [e.word for e in pdo.entries], (node_id, pdo.name)
                cob = node.value(pdo.comm_index, 1)
                assert cob & 0xA00007FF == pdo.cob_id, (node_id, pdo.name, hex(cob))
                assert node.value(pdo.comm_index, 2) == pdo.transmission_type
            assert node.mode == 10
            assert node.value(0x6040) == 0
            assert node.value(0x1017) == master.cfg.master.drive_heartbeat_ms


# --------------------------------------------------------------------------------------------- offline: config check


def findings(cfg: Config) -> tuple[list[str], list[str]]:
    plan = plan_drives(cfg)
    return [f.text for f in plan.errors], plan.refusals


pytestmark_unit = pytest.mark.unit


@pytest.mark.unit
def test_bundled_drive_is_the_default_profile_and_finds_nothing() -> None:
    plan = plan_drives(config(None, layout="shared", fd=True, rate_Hz=1000.0))
    assert plan.findings == []
    p = plan.profiles[0]
    assert (p.current.index, p.current_unit, p.command.index, p.fd) == (0x6078, "permille_rated_current", 0x60B2, True)


@pytest.mark.unit
@pytest.mark.parametrize("variant,drive,error,key", [
    ("only_6077h", {}, "6078h:00: missing", "drives.d.current.object (the drive maps 6077h)"),
    ("vendor_current", {"current": {"object": "30D1h:2"}}, "a vendor current object needs its unit",
     "drives.d.current.unit"),
    ("no_6075h", {}, "6075h:00: missing: the motor's rated current cannot be read", "drives.d.rated_current.object"),
    ("classic", {"current": {"object": "6064h"}}, "6064h:00 'Position actual value'", None),
    ("no_rpdo_deadline", {"rpdo_watchdog": {"object": "2F11h"}}, "2F11h:00: the vendor watchdog object: missing",
     "drives.d.rpdo_watchdog.object"),
])
def test_config_check_names_the_object_and_the_key(variant: str, drive: dict, error: str, key: str | None) -> None:
    errors, refused = findings(config(VARIANTS / f"{variant}.eds", drive))
    assert refused == []
    hits = [e for e in errors if error in e]
    assert hits, errors
    assert all(f"{variant}.eds: joints[" in e and " node " in e for e in hits)
    if key is not None:
        assert all(key in e for e in hits), hits


@pytest.mark.unit
@pytest.mark.parametrize("variant,reason", [
    ("no_cst", "no CST: 6502h supported modes 0x00000080 lack cyclic synchronous torque"),
    ("no_6071h", "no target torque 6071h: the drive cannot be commanded in torque (CST)"),
])
def test_a_drive_without_torque_control_is_refused_with_the_reason(variant: str, reason: str) -> None:
    errors, refused = findings(config(VARIANTS / f"{variant}.eds"))
    assert refused == [reason]
    proc = run_cli("config", "check", "--config", str(_written(config(VARIANTS / f"{variant}.eds"))), check=False)
    assert proc.returncode == 1
    assert f"refused: {reason}" in proc.stdout


def _written(cfg: Config) -> Path:
    """A configuration file in the repository's config folder layout (its robot, relative EDS paths absolute)."""
    import tempfile

    data = cfg.model_dump(mode="json", exclude_none=False)
    data["buses"][0]["interface"] = "socketcan"
    data["buses"][0]["channel"] = "can0"
    data["robot"]["urdf"] = "seed_cobot"
    d = Path(tempfile.mkdtemp(prefix="dragd-profile-"))
    p = d / "cfg.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.mark.unit
def test_config_check_lists_every_problem_at_once_with_keys() -> None:
    """One run lists every missing or unmappable object of every drive, errors and fallbacks, with the key to set."""
    cfg = config(VARIANTS / "vendor_current.eds", {"current": {"object": "30D1h:2"},
                                                   "rated_current": {"object": "2075h"},
                                                   "rpdo_watchdog": {"object": "9999h"}}, layout="compact")
    d = run_cli("config", "check", "--config", str(_written(cfg)), "--json", check=False)
    assert d.returncode == 1
    import json

    out = json.loads(d.stdout)
    texts = [f["text"] for f in out["findings"] if f["level"] == "error"]
    for expect in ("a vendor current object needs its unit; set drives.d.current.unit",
                   "2075h:00: missing: the motor's rated current cannot be read; set drives.d.rated_current.object",
                   "9999h:00: the vendor watchdog object: missing; set drives.d.rpdo_watchdog.object"):
        assert any(expect in t for t in texts), (expect, texts)
    at = [f["at"] for f in out["findings"] if "needs its unit" in f["text"]][0]
    assert "joint1 (node 1, bus arm)" in at and "joint6 (node 6, bus arm)" in at  # grouped over the joints
    assert out["ok"] is False and out["errors"] == len(texts)


@pytest.mark.unit
def test_layouts_without_dummies_and_with_fewer_pdos() -> None:
    """per_node needs no dummy entry; compact and shared-on-FD do, and say which key to change; two RPDOs carry
    per_node; a 32-bit current makes the statusword travel in its own TPDO; drives without TPDO timers get the
    statusword in the SYNC TPDO."""
    no_dummies = VARIANTS / "no_dummies.eds"
    plan = plan_drives(config(no_dummies), budget_findings=False)
    assert plan.errors == []
    words = {e.index for pdos in plan.layouts["arm"].pdos.values() for s in pdos for e in s.entries}
    assert not words & set(range(1, 8))
    errors, _ = findings(config(no_dummies, layout="compact"))
    assert errors and all("[DummyUsage] allows none; set buses[0].layout: per_node" in e for e in errors)
    plan = plan_drives(config(VARIANTS / "two_rpdos.eds"), budget_findings=False)
    assert plan.errors == []
    assert {s.number for s in plan.layouts["arm"].pdos[1] if s.direction == "rpdo"} == {1, 2}
    plan = plan_drives(config(VARIANTS / "vendor_current.eds", {"current": {"object": "30D1h:2", "unit": "mA"}}),
                       budget_findings=False)
    tp = [s for s in plan.layouts["arm"].pdos[1] if s.direction == "tpdo"]
    assert [[e.word for e in s.entries] for s in tp] == [[0x60640020, 0x30D10220], [0x60410010]]
    assert [s.transmission_type for s in tp] == [1, 255]
    plan = plan_drives(config(VARIANTS / "tpdo_no_timers.eds"), budget_findings=False)
    tp = [s for s in plan.layouts["arm"].pdos[1] if s.direction == "tpdo"]
    assert [[e.index for e in s.entries] for s in tp] == [[0x6041, 0x6064, 0x6078]]


@pytest.mark.unit
def test_a_read_only_mapping_is_used_as_it_is_or_left_alone() -> None:
    ro = VARIANTS / "readonly_mapping.eds"
    plan = plan_drives(config(ro, layout="shared"), budget_findings=False)  # classic shared: [sw, pos, cur] = TPDO1's
    assert plan.errors == []
    tp = [s for s in plan.layouts["arm"].pdos[1] if s.direction == "tpdo"]
    assert [(s.number, s.fixed_mapping) for s in tp] == [(1, True)]
    plan = plan_drives(config(ro), budget_findings=False)  # per_node: TPDO1 avoided, RPDO1 [cw] used as it is
    specs = {(s.direction, s.number): s for s in plan.layouts["arm"].pdos[1]}
    assert ("tpdo", 1) not in specs
    assert specs[("rpdo", 1)].fixed_mapping and [e.index for e in specs[("rpdo", 1)].entries] == [0x6040]


@pytest.mark.unit
def test_the_64_bit_limit_and_entry_counts_are_checked_before_anything_is_written() -> None:
    errors, _ = findings(config(VARIANTS / "vendor_current.eds", {"current": {"object": "30D1h:2", "unit": "mA"}},
                                layout="shared"))
    assert errors and all("the cyclic feedback needs 80 bits (6041h (16) + 6064h (32) + 30D1h (32)), more than a "
                          "classic CAN frame's 64" in e for e in errors)
    assert all("set buses[0].layout: per_node" in e for e in errors)


@pytest.mark.unit
def test_per_node_budget_is_honest() -> None:
    """Classic CAN 1 Mbit/s cannot carry SYNC + 6 SYNC RPDOs + 6 SYNC TPDOs at 1 kHz: config check says so with the
    figures; three buses of two joints fit."""
    cfg = config(VARIANTS / "classic.eds", rate_Hz=1000.0)
    plan = plan_drives(cfg)
    load = plan.budget["arm"]["load_pct"]
    assert load > 100.0
    assert any("worst-case bus load" in f.text and "exceeds load_limit_pct 70 %" in f.text for f in plan.errors)


@pytest.mark.unit
def test_config_init_eds_writes_classic_or_fd_as_the_eds_says(tmp_path: Path) -> None:
    out = tmp_path / "c.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(VARIANTS / "classic.eds"), "--out", str(out))
    data = yaml.safe_load(out.read_text())
    assert {b["fd"] for b in data["buses"]} == {False}
    assert {b["layout"] for b in data["buses"]} == {"per_node"}
    assert len(data["buses"]) == 3 and data["loop"]["rate_Hz"] == 1000  # the fewest classic buses at 1 kHz
    assert data["drives"]["classic"]["eds"] == os.path.relpath(VARIANTS / "classic.eds", tmp_path)
    check = run_cli("config", "check", "--config", str(out), "--json")
    assert '"ok": true' in check.stdout
    one = tmp_path / "one.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(VARIANTS / "classic.eds"), "--buses", "1",
            "--out", str(one))
    d1 = yaml.safe_load(one.read_text())
    assert len(d1["buses"]) == 1 and d1["loop"]["rate_Hz"] < 1000
    run_cli("config", "check", "--config", str(one))
    fd = tmp_path / "fd.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(REPO / "canopen_eds" / "joint_drive.eds"),
            "--out", str(fd))
    dfd = yaml.safe_load(fd.read_text())
    assert [(b["fd"], b["layout"]) for b in dfd["buses"]] == [(True, "shared")]
    run_cli("config", "check", "--config", str(fd))


@pytest.mark.unit
def test_a_drive_without_torque_offset_follows_motions_in_cst(tmp_path: Path) -> None:
    """No 60B2h (Eyou): the command is 6071h, which CSP ignores; motions run in CST with dragd's position loop. The
    choice is the profile's (drives.X.motion_mode), forced csp is warned, csp on a drive without CSP is an error."""
    plan = plan_drives(config(VARIANTS / "no_60b2h.eds"))
    p = plan.profiles[0]
    assert (p.command.index, p.motion_mode) == (0x6071, "cst")
    notes = [f.text for f in plan.findings if f.level == "note" and "run in CST" in f.text]
    assert len(notes) == 6 and "the torque command is 6071h, which CiA 402 CSP ignores" in notes[0], notes
    assert not [f for f in plan.findings if f.level != "note"], plan.findings
    assert plan_drives(config(None)).profiles[0].motion_mode == "csp"  # dragd's own drive: CSP + 60B2h, as before
    assert plan_drives(config(VARIANTS / "classic.eds", {"motion_mode": "cst"})).profiles[0].motion_mode == "cst"
    forced = plan_drives(config(VARIANTS / "no_60b2h.eds", {"motion_mode": "csp"}))
    assert forced.profiles[0].motion_mode == "csp"
    warned = [f.text for f in forced.findings if f.level == "warning" and "60B2h" in f.text]
    assert len(warned) == 6 and "the arm sags" in warned[0] and "set drives.d.motion_mode to cst" in warned[0]
    # a drive with 60B2h but without CSP in 6502h follows motions in CST by default; csp is an error with the key
    text = (VARIANTS / "classic.eds").read_text().replace("DefaultValue=0x00000388", "DefaultValue=0x00000208", 1)
    cst_only = tmp_path / "cst_only.eds"
    cst_only.write_text(text)
    assert plan_drives(config(cst_only)).profiles[0].motion_mode == "cst"
    errors, refused = findings(config(cst_only, {"motion_mode": "csp"}))
    assert refused == [] and len(errors) == 6
    assert "drives.d.motion_mode csp: the drive cannot follow position targets (6502h supported modes 0x00000208 " \
           "lack CSP); set drives.d.motion_mode to cst or null" in errors[0]


@pytest.mark.unit
def test_config_init_for_a_cst_motion_drive_sends_no_position_targets(tmp_path: Path) -> None:
    """config init --eds of a drive that follows motions in CST: no 607Ah on the bus (2 buses at 1 kHz instead of 3),
    the CST loop's gains; config check finds nothing refused (identify run, replay and track need no targets)."""
    out = tmp_path / "c.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(VARIANTS / "no_60b2h.eds"), "--out", str(out))
    text = out.read_text()
    data = yaml.safe_load(text)
    assert [b["position_targets"] for b in data["buses"]] == [False, False]
    assert "motions in CST with dragd's position loop need none" in text and "60B2h absent" in text
    assert data["drives"]["no_60b2h"]["torque_command"] == "6071h"
    assert data["drives"]["no_60b2h"]["motion_mode"] == "cst"
    r = data["replay"]
    assert all(len(r[k]) == 6 and min(r[k]) > 0 for k in ("cst_kp_Nm_per_rad", "cst_kd_Nm_s_per_rad",
                                                          "cst_ki_Nm_per_rad_s", "cst_integral_limit_A"))
    check = run_cli("config", "check", "--config", str(out))
    assert "refused" not in check.stdout and "carries no position targets" not in check.stdout, check.stdout
    assert "run in CST" in check.stdout
    classic = tmp_path / "classic.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(VARIANTS / "classic.eds"), "--out", str(classic))
    d = yaml.safe_load(classic.read_text())
    assert {b["position_targets"] for b in d["buses"]} == {True} and "cst_kp_Nm_per_rad" not in d["replay"]
    assert d["drives"]["classic"]["motion_mode"] == "csp"


# --------------------------------------------------------------------------------------------- boot against LocalNodes


BOOTABLE = [
    ("classic", {}),
    ("no_dummies", {}),
    ("no_6075h", {"rated_current": {"object": "3001h:1"}}),
    ("two_rpdos", {}),
    ("bit30_cobids", {}),
    ("only_6077h", {"current": {"object": "6077h"}}),
    ("vendor_current", {"current": {"object": "30D1h:2", "unit": "mA"}}),
    ("readonly_mapping", {}),
    ("no_6007h", {}),
    ("no_rpdo_deadline", {"rpdo_watchdog": {"object": "2F10h"}}),
    ("tpdo_no_timers", {}),
]


@pytest.mark.unit
@pytest.mark.parametrize("variant,drive", BOOTABLE, ids=[v for v, _ in BOOTABLE])
def test_boot_against_drives_built_from_the_eds(variant: str, drive: dict) -> None:
    cfg = config(VARIANTS / f"{variant}.eds", drive, joints=3)
    master, drives, error, log = boot(cfg)
    assert error is None, error
    check_configured(master, drives)
    lines = "\n".join(log)
    assert "protection:" in lines
    n1 = drives.nodes[1]
    if variant == "bit30_cobids":
        tp = [s for s in master.runtimes["arm"].layout.pdos[1] if s.direction == "tpdo"]
        assert all(n1.value(s.comm_index, 1) & 0x4000_0000 for s in tp)  # kept by the drive, accepted by the boot
    if variant == "no_6007h":
        assert "6007h absent" in lines and "605Ah absent" in lines and "6072h absent" in lines
        assert not any(w[0] in (0x6007, 0x605A, 0x6072) for w in n1.writes)
    if variant == "no_rpdo_deadline":
        assert n1.value(0x2F10) == cfg.safety.rpdo_timeout_ms
        assert "no RPDO deadline (140xh has no sub 5); vendor watchdog 2F10h = 50 ms" in lines
    if variant == "readonly_mapping":
        assert not any(w[0] in (0x1A00, 0x1600) for w in n1.writes)  # fixed mappings never written
    if variant == "classic":
        assert "RPDO deadline 50 ms on RPDO1 (1400h:05)" in lines
        assert n1.value(0x1400, 5) == 50 and n1.value(0x6007) == cfg.safety.abort_connection_option
    # only PDOs the drive has were touched
    assert not any(0x1400 <= w[0] <= 0x1BFF and not n1.object_dictionary.get(w[0]) for w in n1.writes)


@pytest.mark.unit
def test_every_failure_of_every_node_in_one_report_and_drives_put_down() -> None:
    """The configuration says classic.eds, the drives are built from no_6007h.eds (no 6007h, 605Ah, 6072h) and one
    reports another rated current: one DriveError lists every failure of each node; every drive is left with
    controlword 0 in pre-operational."""
    cfg = config(VARIANTS / "classic.eds", joints=2)
    wrong = VARIANTS / "no_6007h.eds"
    master, drives, error, _ = boot(cfg, [wrong, wrong], node_facts={2: {(0x6075, 0): 1234}})
    assert error is not None
    assert error.count("problem(s):") == 2
    for index in ("6007h:00 'Abort connection option code'", "605Ah:00 'Quick stop option code'",
                  "6072h:00 'Max torque'"):
        assert error.count(index) == 2, error
    assert "6075h:00 'Motor rated current': rated current 1234 mA = 1.234 A, the configuration says " \
           "joints[1].rated_current_A = 4 A; set joints[1].rated_current_A: 1.234" in error
    assert "0x06020000" in error
    for node in drives.nodes.values():
        assert node.value(0x6040) == 0
        assert node.nmt.state != "OPERATIONAL"


@pytest.mark.unit
def test_a_drive_that_stays_energised_fails_the_boot() -> None:
    cfg = config(VARIANTS / "classic.eds", joints=2)
    master, drives, error, _ = boot(cfg, sticky={2: 0x0027})
    assert error is not None and "node 2" in error
    assert "statusword 0x0027 (operation_enabled) 0.5 s after controlword 0000h (disable voltage)" in error
    assert "node 1" not in error.split("\n", 1)[1]


@pytest.mark.unit
def test_rated_torque_zero_is_written_or_refused() -> None:
    """A drive whose 6076h reads 0 cannot scale torque commands: written with write: true (no_6075h.eds: as EPOS4),
    refused with the key otherwise; a drive's K_m far from the configuration's is reported, not fatal
    (rated_torque_Nm unset)."""
    drive = {"rated_current": {"object": "3001h:1"}}
    cfg = config(VARIANTS / "no_6075h.eds", {**drive, "rated_torque": {"write": True}}, joints=1)
    master, drives, error, log = boot(cfg)
    assert error is None, error
    assert drives.nodes[1].value(0x6076) == round(cfg.joints[0].rated_torque_motor_Nm * 1000)
    assert any("6076h rated torque was 0: wrote 360 mNm (K_m 0.09 N·m/A × rated current 4 A)" in line
               for line in log), log
    cfg = config(VARIANTS / "no_6075h.eds", drive, joints=1)
    master, drives, error, log = boot(cfg, node_facts={1: {(0x6076, 0): 0}})
    assert error is not None and "rated torque 0: the drive cannot scale torque commands" in error
    assert "set drives.d.rated_torque.write: true" in error
    cfg = config(VARIANTS / "classic.eds", joints=1)
    master, drives, error, log = boot(cfg, node_facts={1: {(0x6076, 0): 500}})
    assert error is None
    assert any("the configuration's K_m is 0.09 (+38.9 %)" in line for line in log), log


# --------------------------------------------------------------------------------------------- the vendors' EDS files


VENDORS = {"maxon_epos4": None, "zeroerr_erob": None, "eyou_euservo": None, "wittenstein_simco": None,
           "technosoft_ipos": "no CST: 6502h supported modes 0x001F0065 lack cyclic synchronous torque",
           "schunk_prl120": "no target torque 6071h: the drive cannot be commanded in torque (CST)"}


def _vendor(name: str) -> Path:
    path = EDS_DIR / f"{name}.eds"
    if not path.is_file():
        pytest.skip(f"{path} absent (set DRAGD_EDS_DIR to the fetched vendors' EDS files)")
    return path


@pytest.mark.unit
@pytest.mark.parametrize("name", list(VENDORS))
def test_vendor_eds_config_init_check_and_boot(name: str, tmp_path: Path) -> None:
    """``config init --eds``, ``config check`` and (for drives with CST) the boot against drives built from the
    vendor's EDS; iPOS and PRL120 refused by ``config check`` with the reason."""
    eds = _vendor(name)
    out = tmp_path / "cfg.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(eds), "--out", str(out))
    proc = run_cli("config", "check", "--config", str(out), check=False)
    refusal = VENDORS[name]
    if refusal is not None:
        assert proc.returncode == 1 and f"refused: {refusal}" in proc.stdout, proc.stdout
        return
    assert proc.returncode == 0, proc.stdout
    from dragd.config import load_config

    cfg = load_config(out)
    cfg = cfg.model_copy(update={"buses": [b.model_copy(update={"interface": "virtual"}) for b in cfg.buses]})
    # one bus for the boot test (the budget split is config init's business, tested above)
    data = cfg.model_dump(mode="python")
    data["buses"] = [dict(data["buses"][0], name="arm")]
    for j in data["joints"]:
        j["bus"] = "arm"
    cfg = Config.model_validate({**data, "source": str(out)})
    master, drives, error, log = boot(cfg)
    assert error is None, error
    check_configured(master, drives)
    if name == "maxon_epos4":  # 6076h 0 by default: written from K_m × rated current
        assert drives.nodes[1].value(0x6076) == round(cfg.joints[0].rated_torque_motor_Nm * 1000)
        assert any("6076h rated torque was 0: wrote" in line for line in log)


@pytest.mark.unit
def test_vendor_findings_without_overrides_match_the_issue() -> None:
    """The issue's table: what each vendor EDS lacks, found offline with the default profile."""
    expect = {
        "maxon_epos4": ["6078h:00: missing", "6075h:00: missing"],
        "zeroerr_erob": [],
        "eyou_euservo": ["6078h:00: missing", "6075h:00: missing", "6076h:00: missing"],
        "wittenstein_simco": ["6078h:00 'Current Actual Value': the measured current in a TPDO: not PDO-mappable"],
    }
    for name, errs in expect.items():
        path = EDS_DIR / f"{name}.eds"
        if not path.is_file():
            pytest.skip(f"{path} absent")
        errors, refused = findings(config(path))
        errors = [e for e in errors if "worst-case" not in e]
        assert refused == []
        for e in errs:
            assert any(e in x for x in errors), (name, e, errors)
        assert len({x.split(": ", 2)[2] for x in errors}) == len(errs), (name, errors)  # the same for every joint


# --------------------------------------------------------------------------------------------- process data


class _Sent:
    """A bus that keeps what is sent."""

    def __init__(self) -> None:
        self.frames: dict[int, bytes] = {}

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.frames[msg.arbitration_id] = bytes(msg.data)


@pytest.mark.unit
@pytest.mark.parametrize("variant,drive,layout", [
    ("vendor_current", {"current": {"object": "30D1h:2", "unit": "mA"}}, "per_node"),
    ("only_6077h", {"current": {"object": "6077h"}, "torque_command": "6071h"}, "per_node"),
    ("readonly_mapping", {}, "per_node"),
    ("classic", {}, "shared"),
])
def test_frames_follow_the_eds_types_both_ways(variant: str, drive: dict, layout: str) -> None:
    """Every TPDO decodes by its EDS types into the feedback arrays; every command frame packs controlword, target
    and torque where the mapping puts them (checked with struct codes taken from the EDS, not from the layout)."""
    import struct

    import numpy as np

    from dragd.hardware.io import BusIO
    from dragd.hardware.profile import STRUCT_CODES

    cfg = config(VARIANTS / f"{variant}.eds", drive, joints=3, layout=layout)
    plan = plan_drives(cfg, budget_findings=False)
    assert plan.errors == []
    bus = _Sent()
    io = BusIO(plan.layouts, {"arm": bus}, [1, 2, 3], 127, lambda *a: None)  # type: ignore[dict-item]
    decode = io.tpdo_decoder("arm")
    io.begin_cycle()
    rng = np.random.default_rng(5)
    expect = {}
    for j, node in enumerate((1, 2, 3)):
        p = plan.profiles[j]
        values = {"statusword": 0x0027 + j, "position": int(rng.integers(-2**30, 2**30)),
                  "current": int(rng.integers(-30000, 30000))}
        expect[j] = values
        for spec in plan.layouts["arm"].pdos[node]:
            if spec.direction != "tpdo":
                continue
            codes = "".join(STRUCT_CODES[p.var(e.index, e.subindex).data_type] for e in spec.entries)
            data = struct.pack("<" + codes, *(values[e.field] for e in spec.entries))
            assert decode(spec.cob_id, data)
    fb = io.feedback
    assert fb.rx_count == 3
    for j in range(3):
        assert fb.counts[j] == expect[j]["position"] and fb.statusword[j] == expect[j]["statusword"]
        assert fb.current_permille[j] == expect[j]["current"]
    cw = np.array([0x0F, 0x07, 0x06], dtype=np.int64)
    target = np.array([1000, -2000, 2**30], dtype=np.int64)
    torque = np.array([-32768, 0, 1234], dtype=np.int64)
    io.write(cw, target, torque, 0.0)
    io.flush()
    sources = {"controlword": cw, "target_position": target, "torque": torque}
    for fr in plan.layouts["arm"].frames:
        if fr.direction != "rpdo":
            continue
        data = bus.frames[fr.cob_id]
        for slot in fr.slots:
            p = plan.profiles[slot.joint]
            off = slot.offset
            for f in slot.fields:
                obj = {"controlword": p.controlword, "target_position": p.target_position, "torque": p.command}[f]
                code = STRUCT_CODES[p.var(obj.index, obj.sub).data_type]
                (got,) = struct.unpack_from("<" + code, data, off)
                assert got == sources[f][slot.joint], (fr.name, f)
                off += struct.calcsize("<" + code)


@pytest.mark.unit
def test_a_fixed_mapping_in_an_order_of_its_own_packs_field_by_field() -> None:
    import numpy as np

    from dragd.hardware.io import BusIO
    from dragd.hardware.pdo import BusLayout, FrameLayout, Slot

    fr = FrameLayout("RPDO1 node 1", 0x201, 4, (Slot(0, 0, ("torque", "controlword"), ("h", "H")),), "rpdo", True,
                     1000.0)
    layout = BusLayout("arm", "per_node", False, False, (0,), (1,), {1: []}, [fr])
    bus = _Sent()
    io = BusIO({"arm": layout}, {"arm": bus}, [1], 127, lambda *a: None)  # type: ignore[dict-item]
    io.write(np.array([0x0F], dtype=np.int64), np.array([5], dtype=np.int64), np.array([-300], dtype=np.int64), 0.0)
    assert bus.frames[0x201] == (-300).to_bytes(2, "little", signed=True) + (0x0F).to_bytes(2, "little")


@pytest.mark.unit
def test_scaling_from_the_profile() -> None:
    """Amperes per unit: 6078h per mille of the rated current; 6077h and the command per mille of the rated torque
    (through K_m when rated_torque_Nm is set, else the rated current); a vendor object by its unit."""
    from dragd.hardware.profile import load_profiles
    from dragd.hardware.scaling import Scaling

    cfg = config(VARIANTS / "vendor_current.eds", {"current": {"object": "30D1h:2", "unit": "mA"}}, joints=2)
    sc = Scaling.from_config(cfg, load_profiles(cfg))
    assert list(sc.A_per_permille) == [1e-3, 1e-3]
    assert list(sc.permille_per_A) == [1000.0 / 4.0, 1000.0 / 4.0]
    data = cfg.model_dump(mode="python")
    data["joints"][0]["rated_torque_Nm"] = 0.5  # K_m = 9.09 / 101 = 0.09 N·m/A: 1000 per mille = 5.56 A
    data["drives"]["d"]["current"] = {"object": "6077h"}
    cfg2 = Config.model_validate({**data, "source": cfg.source})
    sc = Scaling.from_config(cfg2, load_profiles(cfg2))
    km = cfg2.joints[0].km_Nm_per_A
    assert sc.A_per_permille[0] == pytest.approx(0.5 / (1000 * km))
    assert sc.permille_per_A[0] == pytest.approx(1000 * km / 0.5)
    assert sc.A_per_permille[1] == 4.0 / 1000.0  # rated_torque_Nm unset: per mille of the rated current


@pytest.mark.unit
def test_layout_auto_chooses_from_what_the_drives_support() -> None:
    plan = plan_drives(config(None, layout="auto", fd=True, rate_Hz=1000.0))
    assert plan.layouts["arm"].kind == "shared"  # dragd's own drive: CAN FD, dummy entries
    plan = plan_drives(config(VARIANTS / "no_dummies.eds", layout="auto", fd=False), budget_findings=False)
    assert plan.layouts["arm"].kind == "per_node" and plan.errors == []


@pytest.mark.unit
def test_bench_all_skips_drive_profiles_without_eds_dir_and_names_it_when_asked() -> None:
    """`dragd bench` (every benchmark) without --eds-dir skips drive_profiles with the reason; named, it is an error."""
    from dragd.lab.bench import BenchError
    from dragd.lab.bench.drives import drive_profiles

    skipped = drive_profiles({"selected": []})
    assert "--eds-dir" in skipped["skipped"]
    with pytest.raises(BenchError, match="--eds-dir DIR"):
        drive_profiles({"selected": ["drive_profiles"]})
