"""Every command in README.md and docs/*.md runs as written.

The commands are read from the documents: each line of a fenced ``sh`` block, and each inline code span that starts
with ``dragd `` or ``./dev ``. Each one is run as a real process (``bash -c``, the installed ``dragd`` first on
PATH) in a fresh copy of a folder holding the files the documents name (plan.npz, log.mcap, params.yaml, ...),
against a simulated robot and daemon (``dragd.lab.rig.Rig``) that ``$DRAGD_SOCKET`` and ``$DRAGD_CONFIG`` point to.

That docs rig runs on the lockstep clock (lockstep tier): the preparation says how long the arm runs (``Rig.sleep``),
and a documented command talking to it runs while its time runs freely (``Rig.running``: as fast as both processes go,
no cycle ever missed), as the user's commands meet a daemon that runs on.

A documented command that starts its own simulator and daemon (``Rule.wall``) runs on the wall clock unless its line
or its rule's ``extra`` says ``--lockstep``; the tier follows (``_param``). What such a command's verdict checks
decides: an experiment (``dragd experiment startup|sine-sweep|drag-quality``: a breakaway found within the ramp, the
figures of seed 001) and a demo scenario (``dragd demo --scenario teach|payload``: waypoints passed, the guard's trip)
check behaviour, so their rules add ``--lockstep`` and they run in the lockstep tier — on the wall clock a host stall
could void them (CI once saw a sine sweep's drives time out after the host froze both processes for 88 ms, and "no
breakaway within the ramp"). What stays on the wall clock is the real-time path itself, whose verdict is that it runs
and reports its timing: the loop benchmarks (figures: a stall is one, with the host's own stalls beside the daemon's
misses) and ``./dev demo`` (the README's main job: its missed cycles beside the machine's stalls).

Each document's commands run in its order against an environment of its own (a fresh folder and docs rig; the
fixture files are made once per test process and copied), so the documents go to whichever xdist worker is free and no
document meets the state another one left. A long run documented word for word in several documents runs once: its
copies take its verdict (``_shared_verdict``, across workers).

How a command runs is decided by ``RULES``, an ordered table of patterns; a command that matches none fails, so a new
documented command needs a rule. The text is changed only by ``./dev X`` → ``dragd X`` (the wrapper only installs
first), by ``PLACEHOLDERS`` (an inline span's FILE, NAME, Q1,...; deployment paths such as /var/lib/dragd/), by an
inline span's notation ([optional] kept, a|b → a), and by a rule's ``extra`` options that shorten long runs.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from dragd.cli.app import build_parser
from dragd.lab.demo import TEACH_STEPS_RAD, guide_and_settle
from dragd.lab.rig import Rig, multicast_group
from dragd.resources import DATA_DIR

pytestmark = pytest.mark.timeout(1800)  # the slow ones: benchmarks generating their 10 min logs once

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
Q0 = [0.0, -0.6, 1.2, -0.6, 1.5708, 0.0]  # the simulated arm's start pose
POSE = ",".join(f"{x:g}" for x in Q0)

# --------------------------------------------------------------------------------------------- extraction

_FENCE = re.compile(r"^\s*```(\S*)\s*$")
_SPAN = re.compile(r"`([^`\n]+(?:\n[^`\n]+)*)`")
_HEREDOC = re.compile(r"<<-?\s*'?\"?(\w+)")


@dataclass(frozen=True)
class Command:
    doc: str
    line: int
    kind: str  # "sh": a line of an sh block, run by a shell as typed; "span": inline notation
    text: str

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}:{self.text[:60]}"


def _strip_comment(line: str) -> str:
    """The line without a trailing ``# comment`` (outside quotes)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def extract(path: Path) -> list[Command]:
    """The commands of one document, in order: sh-block lines (continuations joined, heredoc bodies skipped), then
    the inline ``dragd ...`` / ``./dev ...`` spans of its prose (a span may wrap lines)."""
    commands: list[Command] = []
    prose: list[str] = []
    fence: str | None = None
    heredoc: str | None = None
    pending: tuple[int, str] | None = None
    for n, raw in enumerate(path.read_text().splitlines(), 1):
        m = _FENCE.match(raw)
        if m and heredoc is None:
            fence = m.group(1) if fence is None else None
            prose.append("")
            continue
        if fence is None:
            prose.append(raw)
            continue
        prose.append("")
        if fence != "sh":
            continue
        if heredoc is not None:
            heredoc = None if raw.strip() == heredoc else heredoc
            continue
        start, text = (n, raw) if pending is None else (pending[0], f"{pending[1]} {raw.strip()}")
        text = _strip_comment(text)
        if text.endswith("\\"):
            pending = (start, text[:-1].rstrip())
            continue
        pending = None
        if text.strip():
            commands.append(Command(path.name, start, "sh", text.strip()))
            if (h := _HEREDOC.search(text)) is not None:
                heredoc = h.group(1)
    joined = "\n".join(prose)
    for m in _SPAN.finditer(joined):
        text = " ".join(m.group(1).split())
        if re.match(r"(dragd|\./dev) ", text):
            commands.append(Command(path.name, joined.count("\n", 0, m.start()) + 1, "span", text))
    return commands


ALL = [c for doc in DOCUMENTS for c in extract(doc)]

# --------------------------------------------------------------------------------------------- text → command line

# Inline notation: a placeholder stands for a concrete value (context-keyed where one name means different things).
PLACEHOLDERS: list[tuple[str, str]] = [
    (r"Q1,\.{2,3},Q[N6]", POSE),
    (r"--q \.\.\.", f"--q {POSE}"),
    (r"--dq \.\.\.", "--dq 0.1,0,0,0,0,0"),
    (r"--interp \.\.\.", "--interp spline"),
    (r"\[NAME \.\.\.\]", "compensation_us"),
    (r"teach start NAME", "teach start pick"),
    (r"replay PROGRAM", "replay pick"),
    (r"log summary FILE(\.mcap)?", "log summary log.mcap"),
    (r"(teach show|teach keyframes|replay) FILE", r"\1 pick.yaml"),
    (r"sim \[--config TRUTH\.yaml\]", "sim [--config {repo}/sim/config/seed_cobot.yaml]"),
    (r"--config F\b", "--config {config}"),
    (r"--control SOCKET", "--control {work}/sim.sock"),
    (r"--bus I:C", "--bus udp_multicast:{spare_group}"),
    (r"--robot R\.urdf\b", "--robot arm.urdf"),
    (r"--robot R\b", "--robot seed_cobot"),
    (r"--eds FILE\b", "--eds classic.eds"),  # an in-repo EDS variant (tests/data/eds; vendors' files never committed)
    (r"--eds-dir DIR\b", "--eds-dir eds"),
    (r"--out cfg\.yaml\b", "--out new-cfg.yaml"),  # (the folder has cfg.yaml, made by the same command)
    (r"--params P\b", "--params identified.yaml"),
    (r"--plots DIR", "--plots plots"),
    (r"--plan KIND", "--plan symmetric"),
    (r"--t T\b", "--t 0.2"),
    (r"--cycles N\b", "--cycles 1"),
    (r"--seconds S\b", "--seconds 6"),
    (r"--realtime-priority N\b", "--realtime-priority 70"),
    (r"--speed 0\.1\.\.1", "--speed 0.5"),
    (r"speed X\b", "speed 0.5"),
]
# Deployment paths (sh lines too): the robot controller's folders become the test's.
DEPLOYMENT: list[tuple[str, str]] = [
    (r"/var/lib/dragd/", "{root}/var-lib-dragd/"),  # shared by the commands, as on the controller
    (r"(^|\$\()/opt/dragd/\.venv/bin/", r"\1"),  # the installed dragd and python are first on PATH
    (r"/etc/dragd/dragd\.yaml", "{config}"),
    (r"/tmp/([vr])\b", r"{root}/\1"),  # docs/SYSTEMD.md's scratch folders
]


def first_alternatives(line: str) -> str:
    """Inline notation ``a|b|c`` → ``a`` (for running; the rules see the alternatives)."""
    return re.sub(r"(?<![|\w])([^\s|]+)(\|[^\s|]+)+", r"\1", line)


def command_line(cmd: Command) -> str:
    """The command line a documented command runs as (``{work}``, ``{config}``, ... still to fill in; an inline
    span's alternatives still there: see :func:`first_alternatives`)."""
    text = cmd.text
    text = re.sub(r"^\./dev (dragd|demo|bench)\b",
                  lambda m: "dragd" if m.group(1) == "dragd" else f"dragd {m.group(1)}",
                  text)
    if cmd.kind == "span":
        for pattern, value in PLACEHOLDERS:
            text = re.sub(pattern, value, text)
        text = text.replace("[", "").replace("]", "")
    for pattern, value in DEPLOYMENT:
        text = re.sub(pattern, value, text)
    return text


# --------------------------------------------------------------------------------------------- rules


@dataclass(frozen=True)
class Rule:
    pattern: str  # re.search on the command line (after command_line)
    how: str  # run | service | help | mention | dev | host
    why: str
    extra: str = ""  # options appended (shortest documented options of a long run)
    before: tuple[str, ...] = ()  # preconditions on the rig (see Env.prepare)
    rig: bool = False
    slow: bool = False
    tool: bool = False  # run only where its program is installed
    ready: str = "sim: running"  # a service's line on its output once it serves
    wall: bool = False  # starts its own simulator + daemon: on the wall clock (the rig tier) unless the line or
    #                     ``extra`` says --lockstep (the lockstep tier)


RULES: list[Rule] = [
    # the public UR10e dataset (no licence: not here): options checked; tests/test_ur10e_payload.py runs them with it
    Rule(r"\bDATA/", "mention", "a public dataset's files (tests/test_ur10e_payload.py, tests/test_ur10e_ident.py run "
                               "these when present)"),
    Rule(r"^dragd bench contact_real$", "mention", "the real-data benchmark named in prose (needs --data DATA/: "
                                                   "tests/test_ur10e_contact.py runs it when the dataset is present)"),
    Rule(r"^dragd contact( calibrate| detect)?$", "mention", "a command named in prose"),
    Rule(r"^dragd contact (calibrate|detect)\b", "help",
         "an identified arm and free-motion logs of it: tests/test_contact.py runs both on generated logs, "
         "tests/test_ur10e_contact.py on the real UR10e's"),
    Rule(r"^dragd bench ident_real$", "mention", "the real-data benchmark named in prose (needs --data DATA/: "
                                                 "tests/test_ur10e_ident.py runs it when the dataset is present)"),
    # not run here: root, a systemd host with dragd installed, QEMU or CAN hardware
    Rule(r"^(sudo|sudoedit) ", "host", "root on the robot controller"),
    Rule(r"^(systemctl|journalctl) |^systemd-analyze security dragd", "host", "a systemd host running dragd"),
    Rule(r"^(\w+=\S+ )*tests/vcan/run\b", "host", "the vcan suite (QEMU or CAN interfaces): CI's own step"),
    Rule(r"^python3 -m pip wheel ", "host", "builds the wheel: tests/wheel/run does"),
    Rule(r"^pip install ", "host", "installs into the user's environment (./dev installs the same extras)"),
    Rule(r"^ros2 ", "host", "a full ROS 2 installation on the integrator's machine (docs/ROS2.md)"),
    Rule(r"^python -m can\.(logger|viewer|player) -i dragd_udp ", "mention",
         "python-can's tools on dragd's bus by name: tests/test_python_can_tools.py runs can.logger and can.player"),
    Rule(r"^python -m can\.(logger|viewer) ", "host",
         "python-can's tools with the group routed to lo (root): tests/test_python_can_interop.py runs them in a "
         "network namespace"),
    Rule(r"^\./dev (test|lint|setup)\b", "dev", "the developer wrapper's own commands"),
    # real hardware: parsed, then run with --help
    Rule(r"--bus socketcan:|^dragd run\b", "help", "the daemon on real drives"),
    Rule(r"^dragd view\b|^dragd log view \S+$|^dragd run --rerun$", "help",
         "a Rerun viewer (a display): tests/test_rerun_view.py and tests/test_can_tools.py run them with --save"),
    Rule(r"^dragd log view \S+ --save ", "run", "offline export to .rrd", tool=False),
    Rule(r"^dragd (can scan|sdo (read|write)|nmt) ", "help",
         "a bus no daemon drives (the docs rig's daemon does): tests/test_can_tools.py runs them against the sim"),
    # prose naming a command or option: COMMAND --help names every option given
    Rule(r"^dragd (gap|model|payload|experiment|identify( fit| run)?|log summary|replay --interp|bench identify_\*"
         r"|can scan|sdo read\|write|nmt|log view)$"
         r"|^dragd identify (plan|run)(?!.*--out)", "mention", "a command named in prose"),
    # long-running: started, seen ready, stopped
    Rule(r"^dragd sim --help$", "run", "the simulator's options"),
    Rule(r"^dragd sim\b", "service", "the simulator runs until stopped"),
    Rule(r"^dragd ros2\b", "service", "the ROS 2 bridge runs until stopped (beside the docs' daemon)", rig=True,
         ready="dragd ros2: bridging the daemon"),
    # the daemon's clients, against the rig
    Rule(r"^dragd clock\b", "run", "the lockstep clock's control (docs/LOCKSTEP.md)", before=("lockstep",), rig=True),
    Rule(r"^dragd start\b", "run", "a session's first step: no motion running", before=("no_replay",), rig=True),
    Rule(r"^dragd (status|stop)\b", "run", "control socket", rig=True),
    Rule(r"^dragd mode drag --hold\b", "run", "a drag lease held while it runs (docs/HAND.md): for half a second",
         extra="--seconds 0.5", before=("enabled", "no_replay"), rig=True),
    Rule(r"^dragd mode ", "run", "control socket", before=("enabled", "no_replay"), rig=True),
    Rule(r"^dragd payload (show|set|clear)\b", "run", "control socket", before=("enabled",), rig=True),
    Rule(r"^dragd (payload estimate( --apply)?|check model)$", "mention", "a command named in prose"),
    Rule(r"^dragd payload estimate\b", "run", "slow moves in HOLD", before=("hold",), rig=True, slow=True),
    Rule(r"^dragd check model\b", "run", "slow moves in HOLD", before=("hold",), rig=True, slow=True),
    Rule(r"^dragd teach start ", "run", "teaching", before=("enabled", "no_replay", "new_program"), rig=True),
    Rule(r"^dragd teach mark\b", "run", "teaching: the hand moves the arm first", before=("teaching", "guided"),
         rig=True),
    Rule(r"^dragd teach stop\b", "run", "teaching", before=("teaching",), rig=True),
    Rule(r"^dragd teach list\b", "run", "teaching", rig=True),
    Rule(r"^dragd teach recover\b", "mention", "an interrupted session (tests/test_teach_recover.py kills a daemon "
         "mid-teach and runs it)"),
    Rule(r"^dragd replay \S+ .*--dry-run", "run", "offline plan"),
    Rule(r"^dragd replay (pause|stop|speed)\b", "run", "a running replay", before=("replaying",), rig=True),
    Rule(r"^dragd replay resume\b", "run", "a paused replay", before=("paused",), rig=True),
    Rule(r"^dragd replay status\b", "run", "replay", rig=True),
    Rule(r"^dragd replay \w+", "run", "replay of a taught program",
         before=("no_replay", "home", "enabled", "program"), rig=True),
    Rule(r"^dragd identify run --plan (standard|symmetric)\b", "run", "a real-time identification run",
         extra="--scale 0.1 --joints 6", before=("no_replay", "home", "enabled", "fresh_out"), rig=True, slow=True),
    Rule(r"^dragd identify run ", "run", "a real-time identification run",
         before=("no_replay", "home", "enabled", "fresh_out"), rig=True),
    # offline
    Rule(r"^dragd log ros2$", "mention", "a command named in prose"),
    Rule(r"^dragd (model|config check|log summary|log ros2|teach show|teach keyframes|identify (plan|fit|check)) ",
         "run", "offline"),
    Rule(r"^dragd config check$", "run", "offline"),
    Rule(r"^dragd config init ", "run", "offline"),
    Rule(r"^dragd --version$", "run", "offline"),
    Rule(r"^dragd gap --measured log\.csv --model belief\.yaml --config config\.yaml --json$", "mention",
         "what the gap benchmark runs per case (named in prose)"),
    Rule(r"^dragd gap ", "run", "offline analysis", slow=True),
    Rule(r"^python -m sim log ", "run", "offline simulation"),
    Rule(r"^data=\"\$\(python -m dragd\.resources", "run", "shipped files"),
    Rule(r"^(sed|mkdir|cp|systemd-analyze|systemd-sysusers|systemd-tmpfiles) ", "run", "systemd's offline checks",
         tool=True),
    # long: the shortest documented options
    Rule(r"^dragd demo --scenario payload\b", "run", "sim + daemon (its own length, ~1 min), its verdict behaviour",
         extra="--lockstep", slow=True, wall=True),
    Rule(r"^dragd demo --scenario contact\b", "help",
         "sim + daemon, two sessions (~10 min on a loaded machine): tests/test_contact_daemon.py runs its parts on "
         "the lockstep clock"),
    Rule(r"^dragd demo --scenario teach\b", "run", "sim + daemon, its verdict behaviour",
         extra="--seconds 6 --lockstep", slow=True, wall=True),
    Rule(r"^dragd demo --scenario buttons\b", "help",
         "sim + daemon, ~1.5 min: tests/test_hand_lockstep.py runs the same session (run_buttons_demo, lockstep tier)"),
    Rule(r"^dragd demo\b", "run", "sim + daemon: the real-time path (its timing reported)", extra="--seconds 8",
         slow=True, wall=True),
    Rule(r"^dragd bench --list$", "run", "offline"),
    Rule(r"^dragd bench (compensation_us|bus_load|io_cycle_us|contact_cycle_us)( |$)", "run", "offline"),
    Rule(r"^dragd bench drive_profiles\b", "run", "sim + daemon per EDS file (two in-repo variants here)", slow=True),
    Rule(r"^dragd bench yardstick_us --json$", "run", "offline"),
    Rule(r"^dragd bench (daemon_cpu_us_per_cycle|yardstick_us (compensation_us )?lockstep_)", "run",
         "sim + daemon (wall or lockstep clock)",
         extra="--seconds 3", slow=True, wall=True),
    Rule(r"^dragd bench ros2_", "run", "sim + daemon + the ROS 2 bridge", extra="--seconds 2", slow=True, wall=True),
    Rule(r"^dragd bench fault_matrix\b", "run", "sim + daemon: every injectable fault in turn", slow=True),
    Rule(r"^dragd bench (loop_|--json$)", "run", "sim + daemon (every benchmark: the case matrix cut to two cases)",
         extra="--seconds 3 --cases none__ptp_0,pair__backlash1+payload --jobs 1", slow=True, wall=True),
    Rule(r"^dragd bench gap_confusion\b", "run", "the independent case matrix: two of its cases here (all: ~30 min)",
         extra="--cases none__ptp_0,pair__backlash1+payload --jobs 1", slow=True),
    Rule(r"^dragd bench (identify_|gap_|telemetry_)", "run", "a 10 min log (generated once, cached)", slow=True),
    Rule(r"^dragd experiment startup\b", "run", "sim + daemon, its verdict behaviour",
         extra="--joints 4 --ramp-s 4 --lockstep", before=("identified",), slow=True, wall=True),
    Rule(r"^dragd experiment sine-sweep\b", "run", "sim + daemon, its verdict behaviour",
         extra="--joint 4 --frequencies 8,16 --ramp-s 4 --lockstep", before=("identified",), slow=True, wall=True),
    Rule(r"^dragd experiment drag-quality\b", "run", "sim + daemon, its verdict behaviour",
         extra="--joints 4 --ramp-s 4 --lockstep", before=("identified",), slow=True, wall=True),
]


def rule_for(line: str) -> Rule | None:
    return next((r for r in RULES if re.search(r.pattern, line)), None)


def _long_key(cmd: Command) -> str | None:
    """The key under which a long run (its own sim + daemon, a long offline run) documented word for word in several
    places runs once; None for any other command."""
    rule = rule_for(command_line(cmd))
    if rule is None or not rule.slow or rule.rig or rule.how != "run":
        return None
    raw = first_alternatives(command_line(cmd)) if cmd.kind == "span" else command_line(cmd)
    return f"{raw} {rule.extra}".strip()


def _param(cmd: Command) -> object:
    line = command_line(cmd)
    rule = rule_for(line)
    marks = [pytest.mark.slow] if rule is not None and rule.slow else []
    marks.append(pytest.mark.xdist_group(f"docs:{cmd.doc}"))  # a document's commands in its order, on one worker
    full = f"{line} {rule.extra}" if rule is not None else line  # (the rule's extra options may say --lockstep)
    wall = rule is not None and rule.wall and not re.search(
        r"--lockstep\b|^dragd bench yardstick_us (compensation_us )?lockstep_\w+( lockstep_\w+)* --", full)
    marks.append(pytest.mark.rig if wall else pytest.mark.lockstep)
    return pytest.param(cmd, id=cmd.id, marks=marks)


# --------------------------------------------------------------------------------------------- the environment


def _fixture_files(d: Path, run: Callable[[str], object]) -> None:
    """The files the documents name, made with the documented tools (plans, offline sim logs, fits)."""
    from dragd.lab.demo import TEACH_STEPS_RAD as steps
    from dragd.teach.program import Program, Waypoint, save_program

    run(f"dragd identify plan --kind friction --joints 6 --scale 0.1 --start {POSE} --out plan.npz")
    run(f"dragd identify plan --kind lowspeed --joints 4 --scale 0.1 --start {POSE} --out lowspeed.npz")
    run("python -m sim log --plan lowspeed.npz --out log.mcap")
    run("python -m sim log --plan lowspeed.npz --out log.csv")
    run("python -m sim log --plan plan.npz --out other.mcap")
    run("dragd identify fit --log log.mcap --out params.yaml")
    for src, dst in (("other.mcap", "run.mcap"), ("log.csv", "arm.csv"), ("params.yaml", "params+gap.yaml"),
                     ("log.mcap", "out/demo-fixture.mcap"),
                     ("log.mcap", "../var-lib-dragd/ident.mcap"), ("other.mcap", "../var-lib-dragd/check.mcap")):
        (d / dst).parent.mkdir(exist_ok=True)
        shutil.copy(d / src, d / dst)
    shutil.copy(DATA_DIR.parent / "robots" / "seed_cobot.urdf", d / "arm.urdf")
    cfg = yaml.safe_load((REPO / "config" / "default.yaml").read_text())
    cfg["robot"]["urdf"] = "arm.urdf"
    (d / "arm.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    (d / "eds").mkdir()  # docs/DRIVES.md: a drive's EDS (an in-repo variant) and a folder of them
    for name in ("classic", "no_cst"):
        shutil.copy(REPO / "tests" / "data" / "eds" / f"{name}.eds", d / "eds")
    shutil.copy(REPO / "tests" / "data" / "eds" / "classic.eds", d / "classic.eds")
    run("dragd config init --robot arm.urdf --eds classic.eds --out cfg.yaml")
    q, marks, path = list(Q0), [], []
    for i, step in enumerate(steps):
        q0 = list(q)
        q = [a + b for a, b in zip(q, step, strict=True)]
        for k in range(1 if i else 0, 51):  # 2 s per move at 25 Hz
            path.append([round(2.0 * i + k / 25.0, 4), *(a + (b - a) * k / 50 for a, b in zip(q0, q, strict=True))])
        marks.append(Waypoint(name=f"p{i + 1}", t_s=2.0 * i + 2.0, q_rad=q))
    save_program(Program(name="pick", joints=[f"joint{i}" for i in range(1, 7)], waypoints=marks, path=path),
                 d / "pick.yaml")
    for link in ("config", "systemd", "sim"):  # the checkout's folders the documents run from
        (d / link).symlink_to(REPO / link)


def _kill_session(sid: int) -> list[str]:
    """SIGKILL every process of session ``sid``; their command lines."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if os.getsid(int(d.name)) != sid:
                continue
            found.append((int(d.name), (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")))
            os.kill(int(d.name), signal.SIGKILL)
        except (ProcessLookupError, PermissionError, FileNotFoundError):
            continue
    return [f"{pid}: {cmd.strip()[:120]}" for pid, cmd in found]


class Env:
    """The folders, the rig (started on first use) and the environment the documented commands run in."""

    def __init__(self, root: Path, fixtures: Path | None = None) -> None:
        """``fixtures``: a folder of the fixture files made already (copied; made here where None)."""
        self.root = root
        self.fixtures = root / "fixtures"
        # PATH: the installed entry points beside this Python (a venv's bin), shims for what is missing there
        scripts = Path(sys.executable).parent
        self.bin = root / "bin"
        self.bin.mkdir()
        for name, argv in (("dragd", f"{sys.executable} -m dragd"), ("python", sys.executable)):
            if not (scripts / name).exists():
                (self.bin / name).write_text(f'#!/bin/sh\nexec {argv} "$@"\n')
                (self.bin / name).chmod(0o755)
        self.path = f"{self.bin}{os.pathsep}{scripts}"
        self.config = self._config()
        self.rig: Rig | None = None
        self.marks = 0
        self.runs = 0
        self.spare_group = multicast_group("docs-sim")
        if fixtures is not None:
            shutil.copytree(fixtures, self.fixtures, symlinks=True)
            shutil.copytree(fixtures.parent / "var-lib-dragd", root / "var-lib-dragd")  # (_fixture_files' ../)
        else:
            self.fixtures.mkdir()
            _fixture_files(self.fixtures, lambda line: self.shell(line, self.fixtures, check=True, timeout=600))

    def _config(self) -> Path:
        """The default configuration (its watchdogs: the docs rig runs on the lockstep clock) with the test's program
        folder."""
        data = yaml.safe_load((REPO / "config" / "default.yaml").read_text())
        data["robot"]["urdf"] = "seed_cobot"
        data.setdefault("replay", {})["program_dir"] = str(self.root / "programs")
        path = self.root / "dragd.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path

    @property
    def socket(self) -> str:
        return self.rig.socket if self.rig is not None else str(self.root / "no-rig.sock")

    def environ(self) -> dict[str, str]:
        from ros2_helpers import claim_domain  # (here: it imports rclpy, which collection need not)

        return {**os.environ, "PATH": f"{self.path}{os.pathsep}{os.environ.get('PATH', '')}",
                "DRAGD_SOCKET": self.socket, "DRAGD_CONFIG": str(self.config),
                # a documented `dragd ros2`: DDS discovery on this host, in a domain of this run's own
                "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(claim_domain(100, 199))}

    def fill(self, line: str, work: Path) -> str:
        return (line.replace("{work}", str(work)).replace("{root}", str(self.root))
                .replace("{config}", str(self.config)).replace("{repo}", str(REPO))
                .replace("{spare_group}", self.spare_group))

    def shell(self, line: str, cwd: Path, check: bool = False, timeout: float = 300) -> subprocess.CompletedProcess:
        """Run ``line`` in its own session; whatever it started is gone when this returns (a command timed out or
        one that leaves processes behind would load the machine for every later test)."""
        with subprocess.Popen(["bash", "-c", line], cwd=cwd, env=self.environ(), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True) as p:
            try:
                out, err = p.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                _kill_session(p.pid)
                out, err = p.communicate()
                raise AssertionError(f"{line}: no exit within {timeout:.0f} s\n{out[-3000:]}\n{err[-3000:]}") from None
            left = _kill_session(p.pid)
        proc = subprocess.CompletedProcess(p.args, p.returncode, out, err)
        assert not left, f"{line}: exit {proc.returncode} but left processes running (killed): {left}"
        if check and proc.returncode != 0:
            raise AssertionError(f"{line}: exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        return proc

    def workdir(self) -> Path:
        """A fresh copy of the fixture files (a short path: Unix socket paths have a 108-byte limit)."""
        self.runs += 1
        work = self.root / f"r{self.runs}"
        shutil.copytree(self.fixtures, work, symlinks=True)
        return work

    def identified(self) -> None:
        """identified.yaml as docs/EXPERIMENTS.md makes it: seed 001's friction plan for the tested joint, a log of the
        simulated arm, a fit (once; the experiment rules test joint 4)."""
        if (self.fixtures / "identified.yaml").exists():
            return
        for line in (f"dragd identify plan --kind friction --scale 0.3 --joints 4 --start {POSE} --out friction.npz",
                     "python -m sim log --plan friction.npz --out friction.mcap",
                     "dragd identify fit --log friction.mcap --out identified.yaml"):
            self.shell(line, self.fixtures, check=True, timeout=900)

    # the rig
    def start_rig(self) -> Rig:
        """The docs rig, on the lockstep clock, its time standing still (a command's preparation grants it)."""
        if self.rig is None or not (self.rig.daemon and self.rig.daemon.alive()):
            if self.rig is not None:
                self.rig.close()
            self.rig = Rig("docs", workdir=self.root / f"rig{time.monotonic_ns()}", config=self.config,
                           lockstep=True)
            self.rig.start_sim()
            self.rig.start_daemon()
        self.rig.must("clock", action="pause")  # (docs/LOCKSTEP.md's 'dragd clock run' leaves it running)
        return self.rig

    def stop_rig(self) -> None:
        """A command that starts its own simulator and daemon runs alone (two rigs at 1 kHz overload 2 cores); the
        docs rig starts again when a later command needs it."""
        if self.rig is not None:
            self.rig.close()
            self.rig = None

    def prepare(self, before: tuple[str, ...], line: str = "", work: Path | None = None) -> None:
        """Bring the rig into the state a documented command expects (what the document's previous lines did)."""
        rig = self.start_rig()
        for what in before:
            if what == "fresh_out":  # a run's --out is a new file (it refuses to overwrite)
                out = Path(shlex.split(line)[shlex.split(line).index("--out") + 1])
                (work / out if work is not None else out).unlink(missing_ok=True)
                continue
            status = rig.must("status")
            if what == "home" and float(np.abs(np.asarray(status["q_rad"]) - np.asarray(Q0)).max()) > 0.3:
                # a motion planned from the documented start pose: an arm that earlier commands moved far from it
                # (hand guiding, a replay) starts again from the sim's start pose (a fresh rig)
                self.rig.close()
                self.rig = None
                rig = self.start_rig()
                status = rig.must("status")
            if what == "enabled" and not status.get("drives_enabled"):
                rig.must("start")
            elif what == "hold" and status.get("mode") != "hold":  # payload estimate, check model: from HOLD
                if not status.get("drives_enabled") or status.get("mode") == "fault":
                    rig.must("start")
                rig.must("mode", mode="hold")
                rig.sleep(0.5)
            elif what == "no_replay":
                self._stop_replay(rig, status)
            elif what == "new_program":
                if status.get("teach"):
                    rig.must("teach", action="stop")
                for f in (self.root / "programs").glob("pick.*"):
                    f.unlink()
            elif what == "program" and not self._replayable(self.root / "programs" / "pick.yaml"):
                # (a program taught by an earlier command on this worker, whose recording may be too short to replay,
                # gives way to the fixture's: the commands run in any order, on any worker)
                (self.root / "programs").mkdir(exist_ok=True)
                shutil.copy(self.fixtures / "pick.yaml", self.root / "programs" / "pick.yaml")
            elif what == "teaching" and not status.get("teach"):
                self.prepare(("enabled", "no_replay"))
                rig.must("teach", action="start", name="pick", overwrite=True)
            elif what == "guided":
                guide_and_settle(rig, TEACH_STEPS_RAD[self.marks % len(TEACH_STEPS_RAD)], 1.5, f"p{self.marks + 1}")
                self.marks += 1
            elif what in ("replaying", "paused"):
                replay = status.get("replay") or {}
                if replay.get("outcome") is not None or not replay or (what == "replaying" and
                                                                         replay.get("state") == "paused"):
                    self.prepare(("enabled", "no_replay", "program"))
                    rig.must("replay", program="pick", interp="linear", speed=0.3, cycles=0)
                if what == "paused" and (rig.must("status").get("replay") or {}).get("state") != "paused":
                    rig.must("replay_pause")

    @staticmethod
    def _replayable(path: Path) -> bool:
        """A program at ``path`` with a continuous recording to replay (as the fixture's pick.yaml has)."""
        from dragd.teach.program import load_program

        return path.exists() and len(load_program(path).path_arrays()[0]) >= 2

    @staticmethod
    def _stop_replay(rig: Rig, status: dict) -> None:
        """No teaching session, no motion (a replay or identification run stopped and ended)."""
        if status.get("teach"):
            rig.must("teach", action="stop")
        for _ in range(300):  # 60 s of the arm's time
            if rig.must("status").get("trajectory") is None:
                return
            rig.call("replay_stop")
            rig.sleep(0.2)
        raise AssertionError(f"a motion does not end: {rig.must('status').get('trajectory')}")

    def close(self) -> None:
        if self.rig is not None:
            self.rig.close()


class Envs:
    """This test process's environments: one per document, the current one closed when the next document starts (its
    commands arrive together: their xdist group); the fixture files made once and copied into each."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.made: Env | None = None  # the first environment, whose fixture folder the others copy
        self.current: tuple[str, Env] | None = None
        # the long runs' verdicts, shared by this run's workers (one run's folder: pytest-xdist's workers share the
        # parent of their base temp; without xdist the base temp is the run's own)
        self.verdicts = root / "verdicts"
        self.verdicts.mkdir(parents=True, exist_ok=True)

    def get(self, doc: str) -> Env:
        if self.current is not None and self.current[0] == doc:
            return self.current[1]
        if self.current is not None and self.current[1] is not self.made:
            self.current[1].close()
        e = Env(Path(tempfile.mkdtemp(prefix="docs", dir=self.root)),
                fixtures=self.made.fixtures if self.made is not None else None)
        if self.made is None:
            self.made = e
        elif self.current is not None and self.current[1] is self.made:
            self.made.close()  # (its rig; its fixture folder stays for the next ones)
        self.current = (doc, e)
        return e

    def close(self) -> None:
        for e in {id(x): x for x in (self.made, self.current[1] if self.current else None) if x}.values():
            e.close()


@pytest.fixture(scope="session")  # per test process: the documents go to whichever xdist worker is free
def envs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Envs]:
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    e = Envs(shared / "docs")
    try:
        yield e
    finally:
        e.close()


@contextlib.contextmanager
def _shared_verdict(envs: Envs, key: str) -> Iterator[dict[str, str | None]]:
    """The verdict of the long run ``key``: ``out["first"]``/``out["failure"]`` from the run that ran it first in any
    worker of this test run (waiting while it runs), else empty — then the caller runs it and fills both in."""
    path = envs.verdicts / hashlib.sha256(key.encode()).hexdigest()[:32]
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (held while the first run of it runs)
        out: dict[str, str | None] = json.loads(path.read_text()) if path.exists() else {}
        ran = bool(out)
        yield out
        if not ran and "first" in out:
            path.write_text(json.dumps(out))


# --------------------------------------------------------------------------------------------- the tests


@pytest.mark.unit
def test_the_documents_hold_commands() -> None:
    assert len(ALL) > 50 and {c.doc for c in ALL} >= {"README.md", "TEACH.md", "IDENTIFICATION.md"}


@pytest.mark.unit
@pytest.mark.parametrize("cmd", ALL, ids=lambda c: c.id)
def test_every_command_has_a_rule(cmd: Command) -> None:
    assert rule_for(command_line(cmd)) is not None, (
        f"{cmd.doc}:{cmd.line}: no rule in tests/test_docs_commands.py RULES for '{command_line(cmd)}' "
        f"(documented as '{cmd.text}'): add one saying how it is run")


@pytest.mark.slow  # every documented command against a sim + daemon rig, in CI (./dev test --all); tier per command
@pytest.mark.parametrize("cmd", [_param(c) for c in ALL])
def test_documented_command_runs(cmd: Command, envs: Envs) -> None:
    env = envs.get(cmd.doc)
    line = command_line(cmd)
    rule = rule_for(line)
    if rule is None:
        pytest.fail(f"{cmd.doc}:{cmd.line}: no rule for '{line}'")
    if "identified" in rule.before:
        env.identified()
    work = env.workdir()
    line = env.fill(line, work)
    where = f"{cmd.doc}:{cmd.line}: {cmd.text}\n  ran as: {{}}"
    if rule.how == "host":
        _check_named_files(line)
    elif rule.how == "dev":
        proc = subprocess.run([str(REPO / "dev"), "help"], capture_output=True, text=True, timeout=30)
        assert proc.returncode == 0 and f"./dev {line.split()[1]}" in proc.stdout, proc.stdout
    elif rule.how == "help":
        line = first_alternatives(line) if cmd.kind == "span" else line
        argv = shlex.split(line)[1:]
        build_parser().parse_args(argv)  # every option and value is accepted
        proc = env.shell(f"{line} --help", work, timeout=60)
        assert proc.returncode == 0 and proc.stdout.startswith("usage: dragd"), where.format(f"{line} --help") + \
            f"\n{proc.stdout}\n{proc.stderr}"
    elif rule.how == "mention":
        _check_mention(env, line, work)
    elif rule.how == "service":
        line = first_alternatives(line) if cmd.kind == "span" else line
        if rule.rig:
            env.prepare(rule.before, line, work)
            with env.rig.running():  # (a service beside the daemon paces itself on the wall clock)
                _run_service(env, line, work, where, rule.ready)
        else:
            _run_service(env, line, work, where, rule.ready)
    else:
        if rule.tool and shutil.which(line.split()[0]) is None:
            pytest.skip(f"{line.split()[0]} is not installed here")
        line = first_alternatives(line) if cmd.kind == "span" else line
        # a long run (its own sim + daemon, a long offline run) documented word for word in several places runs once,
        # in the same fixture folder as every copy would: the copies take its verdict
        key = _long_key(cmd)  # (the line before its folders are filled in)
        verdict: contextlib.AbstractContextManager[dict[str, str | None]] = \
            _shared_verdict(envs, key) if key is not None else contextlib.nullcontext({})
        with verdict as shared:
            if shared:
                assert shared["failure"] is None, \
                    where.format(key) + f"\nthe same command failed as {shared['first']}:\n{shared['failure']}"
                return
            if rule.rig:
                env.prepare(rule.before, line, work)
            elif rule.slow:  # its own sim + daemon, or a long offline run: not beside the docs rig
                env.stop_rig()
            full = f"{line} {rule.extra}".strip()
            if rule.rig and "lockstep" not in rule.before:  # the daemon runs on while the command talks to it
                with env.rig.running():
                    proc = env.shell(full, work, timeout=1700 if rule.slow else 300)
            else:
                proc = env.shell(full, work, timeout=1700 if rule.slow else 300)
            failure = None if proc.returncode == 0 else \
                f"exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
            shared.update(first=cmd.id, failure=failure)
        assert failure is None, where.format(full) + f"\n{failure}"


def _check_named_files(line: str) -> None:
    """A host command is not run; the repository's and the shipped files it names must exist."""
    for token in shlex.split(line.split("<<")[0]):
        if token.startswith("$data/"):
            assert (DATA_DIR / token.removeprefix("$data/")).is_file(), f"{token}: not shipped in {DATA_DIR}"
        elif re.match(r"(systemd|config|tests)/", token):
            assert (REPO / token).exists(), f"{token}: not in the repository"


def _check_mention(env: Env, line: str, work: Path) -> None:
    """``dragd WORDS --help`` for each alternative of the command words; it names every option mentioned."""
    tokens = line.split()[1:]
    first_option = next((i for i, t in enumerate(tokens) if t.startswith("-")), len(tokens))
    words, options = tokens[:first_option], [t for t in tokens if t.startswith("--")]
    for choice in (words[-1].split("|") if words and "|" in words[-1] else [None]):
        cmd_words = [w for w in (words[:-1] + [choice] if choice else words) if "*" not in w]
        proc = env.shell(" ".join(["dragd", *cmd_words, "--help"]), work, timeout=60)
        assert proc.returncode == 0, proc.stderr
        for option in options:
            assert option in proc.stdout, f"dragd {' '.join(cmd_words)}: no option {option}"


def _run_service(env: Env, line: str, work: Path, where: str, ready: str = "sim: running") -> None:
    """Started, ready (``ready`` on its output) within 60 s, still running 2 s later, ended by SIGTERM with 0."""
    log = work / "service.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=work, env=env.environ(), stdout=out,
                                stderr=subprocess.STDOUT)
        try:
            end = time.monotonic() + 60
            while time.monotonic() < end and proc.poll() is None and ready not in log.read_text():
                time.sleep(0.2)
            time.sleep(2.0)
            assert proc.poll() is None, where.format(line) + f"\nexited {proc.returncode}:\n{log.read_text()}"
            assert ready in log.read_text(), where.format(line) + f"\nnot ready:\n{log.read_text()}"
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                code = proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                code = proc.wait(5)
    assert code == 0, where.format(line) + f"\nexit {code} after SIGTERM:\n{log.read_text()}"
