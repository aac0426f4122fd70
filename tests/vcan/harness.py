"""The vcan integration suite's harness (started by ``tests/vcan/run``; exit status = the suite's result).

Where the kernel has CAN (AF_CAN sockets work), the selection in this directory runs directly on a local
``vcan0`` (created when missing; root needed for that). Elsewhere -- this project's development machines and
CI, whose kernels are built without CAN -- it runs inside a small throw-away guest whose kernel has CAN:

* kernel: Debian's ``linux-image-<abi>-amd64`` package, downloaded with ``apt-get download`` and unpacked
  (never installed on the host); only ``vmlinuz`` and the virtio / 9p / CAN modules are used;
* userland: ``busybox-static`` (the guest's init, ``insmod``, ``ip``); Python, the project's venv and the
  checkout are the host's own, seen read-only through 9p (a second, writable 9p share carries the exit code);
* hypervisor: QEMU's TCG (``qemu-system-x86``, installed with apt when missing; KVM is not usable on these
  machines), one vCPU, ``-icount shift=0,sleep=off``: the guest's clock is its instruction count (a steady
  1 GIPS CPU, idle time skipped), so its timing does not depend on the host's load.

Everything downloaded or built is cached in ``$DRAGD_VCAN_CACHE`` (default ``~/.cache/dragd-vcan``); a warm
run touches neither apt nor the network. The guest's numba cache is ``$DRAGD_VCAN_CACHE/numba`` (a third 9p share,
``NUMBA_CACHE_DIR``): the simulator's and the daemon's kernels are compiled into it on the host before each boot, for
a generic x86-64 CPU on both sides (``NUMBA_CPU_NAME``), so the guest loads them rather than compiling under TCG.
Delete the directory to rebuild (e.g. for a newer kernel).

Environment:
  DRAGD_VCAN_MODE       auto (default) | guest | local
  DRAGD_VCAN_BUS        the bus of the daemon and the test's CANopen client (default socketcan:vcan0)
  DRAGD_VCAN_SIM_BUS    the simulated drives' bus (default: DRAGD_VCAN_BUS; two wired adapters: socketcan:can1)
  DRAGD_VCAN_LOOP_HZ    the daemon's loop rate (default 100)
  DRAGD_VCAN_PHYSICS_HZ the simulator's physics rate (default 1000)
  DRAGD_VCAN_CACHE      cache directory (default ~/.cache/dragd-vcan; not under /proc, /sys, /dev, /run)
  DRAGD_VCAN_KERNEL     boot this kernel image instead of the cached Debian one (its modules must match)
  DRAGD_VCAN_TIMEOUT_S  wall-clock limit for the guest (default 2400)
"""

from __future__ import annotations

import fcntl
import gzip
import hashlib
import io
import lzma
import os
import re
import shlex
import shutil
import socket
import stat
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
GUEST_INIT = HERE / "guest-init.sh"
DEFAULT_CACHE = Path.home() / ".cache" / "dragd-vcan"
DEFAULT_TIMEOUT_S = 2400.0
MEMORY_MB = 2048
BUSYBOX_PACKAGE = "busybox-static"
KERNEL_META_PACKAGE = "linux-image-amd64"
QEMU_PACKAGE = "qemu-system-x86"
QEMU = "qemu-system-x86_64"
# insmod order (dependencies first): virtio PCI transport, 9p over virtio, CAN core, raw and BCM sockets, vcan
MODULES = ("virtio_ring", "virtio", "virtio_pci_legacy_dev", "virtio_pci_modern_dev", "virtio_pci", "9pnet",
           "9pnet_virtio", "netfs", "fscache", "9p", "can-dev", "can", "can-raw", "can-bcm", "vcan")
GUEST_DONE = "dragd-vcan-guest: suite exited with status"
GUEST_FAILED = "dragd-vcan-guest: FAILED:"
EXIT_HARNESS = 3  # the guest could not be prepared, booted or did not run the suite
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1bc|\r")


class HarnessError(RuntimeError):
    """A step of the harness that failed; the message says what and, where possible, how to fix it."""


def say(msg: str) -> None:
    print(f"vcan: {msg}", flush=True)


def run(argv: list[str], what: str, **kw: object) -> subprocess.CompletedProcess:
    """Run a host command; HarnessError naming ``what`` and the command's output if it fails."""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, **kw)  # type: ignore[call-overload]
    except FileNotFoundError as exc:
        raise HarnessError(f"{what}: {argv[0]} not found ({exc})") from None
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-15:])
        raise HarnessError(f"{what}: `{shlex.join(argv)}` exited with {proc.returncode}:\n{tail}")
    return proc


# ==========================================================================================================
# settings shared by both modes
# ==========================================================================================================
def suite_env() -> dict[str, str]:
    """The DRAGD_VCAN_* settings the selection reads (defaults filled in)."""
    bus = os.environ.get("DRAGD_VCAN_BUS", "socketcan:vcan0")
    return {
        "DRAGD_VCAN_BUS": bus,
        "DRAGD_VCAN_SIM_BUS": os.environ.get("DRAGD_VCAN_SIM_BUS", bus),
        "DRAGD_VCAN_LOOP_HZ": os.environ.get("DRAGD_VCAN_LOOP_HZ", "100"),
        "DRAGD_VCAN_PHYSICS_HZ": os.environ.get("DRAGD_VCAN_PHYSICS_HZ", "1000"),
    }


def bus_channels(env: dict[str, str]) -> list[str]:
    chans = []
    for key in ("DRAGD_VCAN_BUS", "DRAGD_VCAN_SIM_BUS"):
        interface, _, channel = env[key].partition(":")
        if interface != "socketcan" or not channel:
            raise HarnessError(f"{key}={env[key]!r}: expected socketcan:CHANNEL (e.g. socketcan:vcan0)")
        if channel not in chans:
            chans.append(channel)
    return chans


def pytest_argv(python: str, extra: list[str], basetemp: str) -> list[str]:
    return [python, "-m", "pytest", "tests/vcan", "-v", "-p", "no:cacheprovider", f"--basetemp={basetemp}",
            "--durations=8", *extra]


def kernel_has_can() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        return True
    except (OSError, AttributeError):
        return False


# ==========================================================================================================
# local mode: this kernel has CAN
# ==========================================================================================================
def ensure_local_vcan(channel: str) -> None:
    """Make sure ``channel`` exists, is up and (vcan) carries CAN FD frames (MTU 72)."""
    net = Path("/sys/class/net") / channel
    root = os.geteuid() == 0
    if not net.exists():
        if not channel.startswith("vcan"):
            raise HarnessError(f"no network interface {channel!r}: bring the CAN interface up first, e.g. "
                               f"`ip link set {channel} up type can bitrate 1000000 dbitrate 5000000 fd on`")
        if not root:
            raise HarnessError(f"no interface {channel!r} and not root: run `sudo modprobe vcan; sudo ip link add "
                               f"dev {channel} type vcan; sudo ip link set {channel} mtu 72 up` first")
        if shutil.which("modprobe"):
            subprocess.run(["modprobe", "vcan"], capture_output=True)  # may be built in; `ip` says if it is missing
        run(["ip", "link", "add", "dev", channel, "type", "vcan"], f"creating {channel}")
    if channel.startswith("vcan") and (net / "mtu").read_text().strip() != "72":
        if not root:
            raise HarnessError(f"{channel} has MTU {(net / 'mtu').read_text().strip()}: CAN FD needs 72 "
                               f"(`sudo ip link set {channel} mtu 72`)")
        run(["ip", "link", "set", channel, "down"], f"setting {channel} down")
        run(["ip", "link", "set", channel, "mtu", "72"], f"setting {channel}'s MTU to 72 (CAN FD)")
    if "up" not in (net / "operstate").read_text() and not int((net / "flags").read_text(), 16) & 1:
        if not root:
            raise HarnessError(f"{channel} is down: `sudo ip link set {channel} up`")
        run(["ip", "link", "set", channel, "up"], f"setting {channel} up")


def run_local(extra: list[str]) -> int:
    if not kernel_has_can():
        raise HarnessError("DRAGD_VCAN_MODE=local, but this kernel refuses AF_CAN sockets (no CAN support); "
                           "use the guest (DRAGD_VCAN_MODE=auto or guest)")
    env = suite_env()
    for channel in bus_channels(env):
        ensure_local_vcan(channel)
    python = str(REPO / ".venv" / "bin" / "python")
    basetemp = tempfile.mkdtemp(prefix="dragd-vcan-")
    say(f"this kernel has CAN: running the selection on {env['DRAGD_VCAN_BUS']} directly (no guest)")
    proc = subprocess.run(pytest_argv(python, extra, basetemp), cwd=REPO, env={**os.environ, **env})
    if proc.returncode == 0:
        shutil.rmtree(basetemp, ignore_errors=True)
    return report_pytest_status(proc.returncode)


def report_pytest_status(rc: int) -> int:
    if rc == 5:
        say("FAILED: pytest collected no test (exit status 5); the vcan selection must run")
        return 1
    if rc != 0:
        say(f"FAILED: the vcan selection exited with status {rc}")
    return rc


# ==========================================================================================================
# guest mode: prepare (cached), boot, collect the result
# ==========================================================================================================
class Guest:
    """Paths of one prepared guest: kernel image, initramfs, busybox."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.kernel = root / "vmlinuz"
        self.initrd = root / "initrd.gz"
        self.busybox = root / "busybox"
        self.stamp = root / "complete"

    def complete(self) -> bool:
        return self.stamp.exists() and all(p.exists() for p in (self.kernel, self.initrd, self.busybox))


def apt_env() -> dict[str, str]:
    return {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}


def apt_update_once(state: dict[str, bool]) -> None:
    if not state.get("updated"):
        say("apt-get update ...")
        run(["apt-get", "update", "-q"], "apt-get update (needed to find Debian's packages)", env=apt_env())
        state["updated"] = True


def resolve_kernel_package(state: dict[str, bool]) -> str:
    """The versioned kernel package linux-image-amd64 currently depends on (e.g. linux-image-6.1.0-56-amd64)."""
    for attempt in range(2):
        proc = subprocess.run(["apt-cache", "depends", KERNEL_META_PACKAGE], capture_output=True, text=True)
        found = re.findall(r"Depends:\s+(linux-image-\S+-amd64)\b", proc.stdout)
        if found:
            return found[0]
        if attempt == 0:
            apt_update_once(state)
    raise HarnessError(f"cannot resolve {KERNEL_META_PACKAGE} with apt-cache (is this a Debian/Ubuntu machine with "
                       f"its package lists reachable?):\n{proc.stdout}{proc.stderr}")


def apt_download(package: str, dest: Path, state: dict[str, bool]) -> Path:
    """``apt-get download PACKAGE`` into ``dest`` (cached: an existing .deb of the package is reused)."""
    dest.mkdir(parents=True, exist_ok=True)
    have = sorted(dest.glob(f"{package}_*.deb"))
    if have:
        return have[-1]
    for attempt in range(2):
        say(f"downloading {package} ...")
        proc = subprocess.run(["apt-get", "download", "-q", "-o", "APT::Sandbox::User=root", package], cwd=dest,
                              capture_output=True, text=True, env=apt_env())
        have = sorted(dest.glob(f"{package}_*.deb"))
        if proc.returncode == 0 and have:
            return have[-1]
        if attempt == 0:
            apt_update_once(state)
    raise HarnessError(f"apt-get download {package} failed ({proc.returncode}):\n{proc.stdout}{proc.stderr}")


def deb_pick(deb: Path, wanted: Callable[[str], object]) -> dict[str, bytes]:
    """The regular files of a .deb's data archive whose names (``./boot/...``) ``wanted`` accepts, in one pass (the
    kernel's archive is ~400 MB unpacked: each pass costs seconds of CPU)."""
    picked: dict[str, bytes] = {}
    with subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE) as p:
        assert p.stdout is not None
        with tarfile.open(fileobj=p.stdout, mode="r|") as tar:
            for m in tar:
                if not m.isfile() or not wanted(m.name):
                    continue
                src = tar.extractfile(m)
                assert src is not None
                picked[m.name] = src.read()
        if p.wait() != 0:
            raise HarnessError(f"dpkg-deb --fsys-tarfile {deb.name} failed ({p.returncode}); delete it to download it "
                               "again")
    return picked


def cpio_newc(entries: list[tuple[str, int, bytes, tuple[int, int]]]) -> bytes:
    """An initramfs (cpio 'newc'): entries of (path, mode, data, (rdev major, minor)); then the trailer."""
    out = io.BytesIO()

    def put(name: str, mode: int, data: bytes, rdev: tuple[int, int], ino: int) -> None:
        encoded = name.encode() + b"\0"
        fields = (ino, mode, 0, 0, 1, 0, len(data), 0, 0, rdev[0], rdev[1], len(encoded), 0)
        out.write(b"070701" + b"".join(b"%08X" % f for f in fields) + encoded)
        out.write(b"\0" * (-out.tell() % 4))
        out.write(data)
        out.write(b"\0" * (-out.tell() % 4))

    for ino, (name, mode, data, rdev) in enumerate(entries, start=1):
        put(name, mode, data, rdev, ino)
    put("TRAILER!!!", 0, b"", (0, 0), 0)
    return out.getvalue()


INITRAMFS_INIT = r"""#!/bin/busybox sh
# dragd vcan guest, stage 1 (initramfs): load the modules, mount the host's root read-only over 9p, switch to it.
export PATH=/bin
fail() { echo "dragd-vcan-guest: FAILED: $*"; /bin/busybox poweroff -f; }
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t devtmpfs dev /dev || fail "mounting devtmpfs"
for m in @MODULES@; do /bin/busybox insmod /lib/modules/$m.ko || fail "insmod $m (kernel and modules must match)"; done
/bin/busybox mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144,ro,cache=loose hostroot /host \
  || fail "mounting the host's root (9p tag hostroot)"
[ -x "/host$dragd_busybox" ] && [ -f "/host$dragd_init" ] \
  || fail "not found in the host's root: $dragd_busybox or $dragd_init"
/bin/busybox mount --move /dev /host/dev || fail "moving /dev"
/bin/busybox umount /proc
exec /bin/busybox switch_root /host "$dragd_busybox" sh "$dragd_init"
"""


def build_hash() -> str:
    """What the cached guest depends on besides the packages: this builder's initramfs recipe."""
    return hashlib.sha256((INITRAMFS_INIT + " ".join(MODULES)).encode()).hexdigest()[:12]


def module_paths(names: list[str], kver_dir: str) -> dict[str, str]:
    """Map each module to its member in the kernel .deb (.ko, or .ko.xz on newer kernels)."""
    out = {}
    for mod in MODULES:
        hits = [n for n in names if n.startswith(f"./lib/modules/{kver_dir}/")
                and re.search(rf"/{re.escape(mod)}\.ko(\.xz)?$", n)]
        if not hits:
            raise HarnessError(f"the kernel package has no module {mod}.ko (needed: {', '.join(MODULES)})")
        out[mod] = hits[0]
    return out


def prepare_guest(cache: Path) -> Guest:
    """The cached guest for this harness version, built (download, unpack, initramfs) if missing."""
    cache.mkdir(parents=True, exist_ok=True)
    current = cache / "current"
    if current.is_file():
        guest = Guest(cache / current.read_text().strip())
        if guest.complete() and guest.root.name.endswith(build_hash()):
            return guest
    for tool in ("apt-get", "apt-cache", "dpkg-deb"):
        if shutil.which(tool) is None:
            raise HarnessError(f"{tool} not found: the guest is built from Debian packages (a Debian or Ubuntu host "
                               "is needed), or run on a machine whose kernel has CAN (see docs/VCAN.md)")
    state: dict[str, bool] = {}
    kpkg = resolve_kernel_package(state)
    debs = cache / "debs"
    kdeb = apt_download(kpkg, debs, state)
    bdeb = apt_download(BUSYBOX_PACKAGE, debs, state)
    guest = Guest(cache / f"guest-{kdeb.stem}-{build_hash()}")
    if not guest.complete():
        say(f"building the guest from {kdeb.name} and {bdeb.name} ...")
        tmp = Path(tempfile.mkdtemp(prefix="build-", dir=cache))
        try:
            ko = re.compile(rf"/({'|'.join(map(re.escape, MODULES))})\.ko(\.xz)?$")
            files = deb_pick(kdeb, lambda n: n.startswith("./boot/vmlinuz-")
                             or (n.startswith("./lib/modules/") and ko.search(n) is not None))
            vmlinuz = [n for n in files if n.startswith("./boot/vmlinuz-")]
            if not vmlinuz:
                raise HarnessError(f"{kdeb.name} has no /boot/vmlinuz-*")
            kver = vmlinuz[0].split("vmlinuz-", 1)[1]
            mods = module_paths(list(files), kver)
            (tmp / "vmlinuz").write_bytes(files[vmlinuz[0]])
            busybox = deb_pick(bdeb, lambda n: n == "./bin/busybox")
            if not busybox:
                raise HarnessError(f"{bdeb.name} lacks ./bin/busybox")
            (tmp / "busybox").write_bytes(busybox["./bin/busybox"])
            (tmp / "busybox").chmod(0o755)
            entries: list[tuple[str, int, bytes, tuple[int, int]]] = [
                (d, stat.S_IFDIR | 0o755, b"", (0, 0)) for d in ("bin", "dev", "host", "lib", "lib/modules", "proc")]
            entries.append(("dev/console", stat.S_IFCHR | 0o600, b"", (5, 1)))
            entries.append(("bin/busybox", stat.S_IFREG | 0o755, (tmp / "busybox").read_bytes(), (0, 0)))
            for k, member in mods.items():
                data = files[member]
                if member.endswith(".xz"):
                    data = lzma.decompress(data)
                entries.append((f"lib/modules/{k}.ko", stat.S_IFREG | 0o644, data, (0, 0)))
            init = INITRAMFS_INIT.replace("@MODULES@", " ".join(MODULES)).encode()
            entries.append(("init", stat.S_IFREG | 0o755, init, (0, 0)))
            (tmp / "initrd.gz").write_bytes(gzip.compress(cpio_newc(entries), compresslevel=6))
            guest.root.mkdir(exist_ok=True)
            for f in (tmp / "vmlinuz", tmp / "initrd.gz", tmp / "busybox"):
                f.replace(guest.root / f.name)
            guest.stamp.write_text(f"{kdeb.name}\n{bdeb.name}\n")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    current.write_text(guest.root.name + "\n")
    for old in cache.glob("guest-*"):  # keep only the guest in use
        if old != guest.root:
            shutil.rmtree(old, ignore_errors=True)
    return guest


def ensure_qemu() -> str:
    found = shutil.which(QEMU)
    if found:
        return found
    if os.geteuid() != 0:
        raise HarnessError(f"{QEMU} not found and not root: install it (`sudo apt-get install --no-install-recommends "
                           f"{QEMU_PACKAGE}`) or run on a machine whose kernel has CAN")
    say(f"installing {QEMU_PACKAGE} with apt-get (once per machine) ...")
    argv = ["apt-get", "install", "-y", "-q", "--no-install-recommends", QEMU_PACKAGE]
    if subprocess.run(argv, capture_output=True, text=True, env=apt_env()).returncode != 0:
        apt_update_once({})
        run(argv, f"installing {QEMU_PACKAGE}", env=apt_env())
    found = shutil.which(QEMU)
    if not found:
        raise HarnessError(f"{QEMU_PACKAGE} is installed but {QEMU} is not on PATH")
    return found


def check_guest_paths(paths: dict[str, Path]) -> None:
    for what, p in paths.items():
        text = str(p)
        if any(c.isspace() for c in text) or len(text) > 200:
            raise HarnessError(f"{what} {text!r}: the guest needs a path without white space, at most 200 characters")
        if text.startswith(("/proc/", "/sys/", "/dev/", "/run/")):
            raise HarnessError(f"{what} {text!r}: the guest mounts its own /proc, /sys, /dev and /run over the host's; "
                               "use another location")


def write_guest_env(share: Path, extra: list[str]) -> None:
    python = REPO / ".venv" / "bin" / "python"
    env = {**suite_env(), "REPO": str(REPO), "PYTHON": str(python), "SHARE": str(share),
           "NUMBA_CPU_NAME": GUEST_NUMBA_CPU}
    lines = [f"{k}={shlex.quote(v)}" for k, v in env.items()]
    lines.append("set -- " + " ".join(shlex.quote(a) for a in pytest_argv(str(python), extra, "/run/tmp/pytest")))
    (share / "guest.env").write_text("\n".join(lines) + "\n")


class Console(threading.Thread):
    """Pumps the guest's serial console to our stdout and a log file."""

    def __init__(self, proc: subprocess.Popen, log: Path) -> None:
        super().__init__(daemon=True)
        self.proc = proc
        self.log = log
        self.lines: list[str] = []

    def run(self) -> None:
        assert self.proc.stdout is not None
        t0 = time.monotonic()
        with self.log.open("w") as fh:
            for raw in self.proc.stdout:
                line = _ANSI.sub("", raw.decode(errors="replace")).rstrip("\n")
                fh.write(f"[{time.monotonic() - t0:7.1f} s] {line}\n")  # host wall time since QEMU started
                fh.flush()
                self.lines.append(line)
                if line.strip() and not line.startswith(("SeaBIOS", "Booting from ROM")):
                    print(line, flush=True)


# numba keys a cached kernel by the CPU it was compiled for (LLVM's name and features): TCG's -cpu max is not the host's
# CPU, so the guest and the host's prebuild below both compile for a generic x86-64 (numba: features "" with it)
GUEST_NUMBA_CPU = "generic"
PREBUILT_FLAG = "prebuilt"  # in the run's share once the prebuild has ended (built or not): guest-init.sh waits for it
# every module's kernels as the simulator's and the daemon's processes compile them (dragd.jit.compile_kernels, once per
# module, with the cycle's argument types); boot() reports any kernel the guest still had to compile itself
PREBUILD = """
from dragd.control import contact, contact_watch, fused, guard, safety
from dragd.daemon import kernels
from sim import kernels as sim_kernels
for compile_ in (fused._compiled, guard._kernels, safety.safety_kernel, contact.contact_kernels, contact_watch._kernels,
                 kernels.kernels, sim_kernels.hold_kernel):
    assert compile_() is not None, compile_
"""


def prebuild_kernels(numba_cache: Path) -> float:
    """Compile the simulator's and the daemon's numba kernels on the host, natively, into the guest's numba cache: the
    guest sees the same sources, venv and cache directory (9p), so its cache index matches and it loads them instead
    of compiling them under TCG, which took most of a cold run (~8 s of CPU here, ~20x that in the guest, in each
    first process of a kind). Kernels cached already: ~1 s. Returns the time taken. A failure only leaves the guest
    to compile them itself."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(NUMBA_CPU_NAME=GUEST_NUMBA_CPU, NUMBA_CACHE_DIR=str(numba_cache))
    t0 = time.monotonic()
    try:
        proc = subprocess.run([str(REPO / ".venv/bin/python"), "-c", PREBUILD], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as e:
        say(f"the kernels were not prebuilt for the guest ({e}): it compiles them itself")
        return time.monotonic() - t0
    if proc.returncode != 0:
        say(f"the kernels were not prebuilt for the guest (exit {proc.returncode}): it compiles them itself\n"
            f"{proc.stderr[-2000:]}")
    return time.monotonic() - t0


def cached_kernels(numba_cache: Path) -> dict[str, float]:
    """numba's index files in the cache (one per compiled function), with their mtimes."""
    return {str(p.relative_to(numba_cache)): p.stat().st_mtime for p in numba_cache.rglob("*.nbi")}


def boot(guest: Guest, qemu: str, extra: list[str], cache: Path, timeout_s: float) -> int:
    kernel = Path(os.environ["DRAGD_VCAN_KERNEL"]) if os.environ.get("DRAGD_VCAN_KERNEL") else guest.kernel
    if not kernel.is_file():
        raise HarnessError(f"the guest cannot start: kernel image {kernel} does not exist")
    runs = cache / "runs"
    runs.mkdir(exist_ok=True)
    for old in sorted(runs.glob("run-*"), key=lambda p: p.stat().st_mtime)[:-5]:  # keep the last failed runs' logs
        shutil.rmtree(old, ignore_errors=True)
    share = Path(tempfile.mkdtemp(prefix="run-", dir=runs))
    numba_cache = cache / "numba"  # the guest's compiled kernels, kept across boots (compiling them under TCG took
    numba_cache.mkdir(exist_ok=True)  # most of a run's start-up; numba's index follows the sources' path and mtime)
    prebuilt: dict[str, float] = {}

    def prebuild() -> None:  # beside the guest's boot (QEMU's one thread): the guest waits for PREBUILT_FLAG
        try:
            took = prebuild_kernels(numba_cache)
            prebuilt.update(cached_kernels(numba_cache))
            say(f"numba kernels for the guest ({GUEST_NUMBA_CPU} CPU) prebuilt on the host in {took:.1f} s: "
                f"{len(prebuilt)} cached")
        finally:
            (share / PREBUILT_FLAG).touch()

    builder = threading.Thread(target=prebuild, name="numba-prebuild", daemon=True)
    check_guest_paths({"the repository": REPO, "the cache": cache, "the venv's python": REPO / ".venv/bin/python"})
    write_guest_env(share, extra)
    argv = [qemu, "-accel", "tcg,thread=single", "-icount", "shift=0,sleep=off", "-cpu", "max", "-smp", "1",
            "-m", str(MEMORY_MB), "-nodefaults", "-display", "none", "-monitor", "none", "-no-reboot",
            "-chardev", "stdio,id=console,signal=off", "-serial", "chardev:console",
            "-kernel", str(kernel), "-initrd", str(guest.initrd),
            "-append", f"console=ttyS0 quiet panic=-1 dragd_busybox={guest.busybox} dragd_init={GUEST_INIT} "
                       f"dragd_share={share}",
            "-virtfs", "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
            "-virtfs", f"local,path={share},mount_tag=share,security_model=none,multidevs=remap",
            "-virtfs", f"local,path={numba_cache},mount_tag=numba,security_model=none,multidevs=remap"]
    say(f"booting the guest ({kernel.name}, QEMU TCG, 1 vCPU, icount) ...")
    t0 = time.monotonic()
    builder.start()
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    console = Console(proc, share / "console.log")
    console.start()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)
        console.join(5)
        raise HarnessError(f"the guest did not finish within {timeout_s:.0f} s (DRAGD_VCAN_TIMEOUT_S); "
                           f"console log: {share / 'console.log'}") from None
    console.join(10)
    took = time.monotonic() - t0
    rc_file = share / "rc"
    failed = [ln for ln in console.lines if GUEST_FAILED in ln]
    if not rc_file.exists():
        tail = "\n".join(console.lines[-25:])
        reason = failed[0].split(GUEST_FAILED, 1)[1].strip() if failed else (
            f"QEMU exited with status {proc.returncode} before the guest ran the suite")
        raise HarnessError(f"the guest could not run the suite: {reason}\n--- console (last lines) ---\n{tail}\n"
                           f"--- full console log: {share / 'console.log'}")
    rc = int(rc_file.read_text().strip() or "1")
    builder.join()
    compiled = sorted(k for k, m in cached_kernels(numba_cache).items() if prebuilt.get(k) != m)
    if compiled:  # the prebuild missed these (a new kernel module or signature): add them to PREBUILD
        say(f"the guest compiled {len(compiled)} numba kernel(s) itself under TCG: {', '.join(compiled)}")
    say(f"guest finished in {took:.0f} s (wall), suite exit status {rc}")
    if rc == 0:
        shutil.rmtree(share, ignore_errors=True)
    else:
        say(f"console log kept: {share / 'console.log'}")
    return rc


def run_guest(extra: list[str]) -> int:
    env = suite_env()
    chans = bus_channels(env)
    if any(not c.startswith("vcan") for c in chans):
        raise HarnessError(f"buses {', '.join(chans)}: the guest only has vcan0; real interfaces need a kernel with "
                           "CAN (DRAGD_VCAN_MODE=local)")
    cache = Path(os.environ.get("DRAGD_VCAN_CACHE") or DEFAULT_CACHE).resolve()
    t0 = time.monotonic()
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one preparation at a time per cache
        guest = prepare_guest(cache)
        qemu = ensure_qemu()
    # bytecode for the checkout's modules (the guest's view is read-only; .venv is compiled by pip already)
    subprocess.run([str(REPO / ".venv/bin/python"), "-m", "compileall", "-q", "-j", "0", "dragd", "sim", "tests"],
                   cwd=REPO, capture_output=True)
    say(f"guest ready in {time.monotonic() - t0:.1f} s ({guest.root})")
    timeout_s = float(os.environ.get("DRAGD_VCAN_TIMEOUT_S", DEFAULT_TIMEOUT_S))
    return report_pytest_status(boot(guest, qemu, extra, cache, timeout_s))


def main(argv: list[str]) -> int:
    if argv[:1] in (["-h"], ["--help"]):
        print(__doc__)
        print("usage: tests/vcan/run [PYTEST ARGS ...]   (e.g. -k flow)")
        return 0
    mode = os.environ.get("DRAGD_VCAN_MODE", "auto")
    if mode not in ("auto", "guest", "local"):
        say(f"DRAGD_VCAN_MODE={mode!r}: expected auto, guest or local")
        return 2
    t0 = time.monotonic()
    try:
        if mode == "local" or (mode == "auto" and kernel_has_can()):
            rc = run_local(argv)
        else:
            if mode == "auto":
                say("this kernel has no CAN (AF_CAN sockets refused): running the selection in a guest")
            rc = run_guest(argv)
    except HarnessError as exc:
        say(f"FAILED: {exc}")
        say("the vcan suite did not run: this is a failure, not a skip")
        return EXIT_HARNESS
    except Exception:  # noqa: BLE001 - a harness bug: still a loud failure with exit status 3
        import traceback

        traceback.print_exc()
        say("FAILED: the harness itself failed (traceback above); the vcan suite did not run")
        return EXIT_HARNESS
    say(f"total {time.monotonic() - t0:.0f} s, exit status {rc}")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
