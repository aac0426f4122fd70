# dragd vcan guest, stage 2: PID 1 in the host's root filesystem (read-only over 9p), run by busybox sh.
# Set up by tests/vcan/harness.py; the kernel command line gives dragd_busybox, dragd_init and dragd_share.
# Mounts what a system needs, creates vcan0 (CAN FD: MTU 72), runs the pytest selection of guest.env and
# writes its exit status to the writable share, then powers off. Any failure before pytest says so and
# writes no status (the harness reports it as "the guest could not run the suite").
B="$dragd_busybox"
say() { echo "dragd-vcan-guest: $*"; }
fail() { say "FAILED: $*"; $B sync; $B poweroff -f; }

$B mount -t proc proc /proc || fail "mounting /proc"
$B mount -t sysfs sys /sys || fail "mounting /sys"
$B mount -t tmpfs -o mode=0755 run /run || fail "mounting a tmpfs on /run"
$B mkdir -p /dev/pts /dev/shm /run/tmp /run/home
$B mount -t devpts devpts /dev/pts
$B mount -t tmpfs shm /dev/shm
$B mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 share "$dragd_share" \
  || fail "mounting the writable share (9p tag share) on $dragd_share"
[ -f "$dragd_share/guest.env" ] || fail "no guest.env in the share"
# the numba kernels, prebuilt on the host for NUMBA_CPU_NAME (tests/vcan/harness.py); without it: compiled here
$B mkdir -p /run/numba
$B mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 numba /run/numba \
  || say "no numba cache share (9p tag numba): kernels compile at this boot"
. "$dragd_share/guest.env"

$B ip link set lo up
for chan in "${DRAGD_VCAN_BUS#socketcan:}" "${DRAGD_VCAN_SIM_BUS#socketcan:}"; do
  [ -e "/sys/class/net/$chan" ] && continue
  $B ip link add dev "$chan" type vcan || fail "creating $chan (ip link add dev $chan type vcan)"
  $B ip link set "$chan" mtu 72 || fail "setting $chan's MTU to 72 (CAN FD)"
  $B ip link set "$chan" up || fail "setting $chan up"
  say "$chan up, MTU $($B cat /sys/class/net/$chan/mtu)"
done

cd "$REPO" || fail "no repository at $REPO"
[ -x "$PYTHON" ] || fail "no venv python at $PYTHON"
# the host compiles the numba kernels into /run/numba while this guest boots (tests/vcan/harness.py): wait for it
# (the guest's idle time costs no wall time under icount sleep=off; the harness's wall-clock limit guards this)
[ -e "$SHARE/prebuilt" ] || say "waiting for the host's numba prebuild"
while [ ! -e "$SHARE/prebuilt" ]; do $B sleep 1; done
say "running: $*"
HOME=/run/home TMPDIR=/run/tmp MPLCONFIGDIR=/run/home/mpl XDG_CACHE_HOME=/run/home/cache NUMBA_CACHE_DIR=/run/numba NUMBA_CPU_NAME="$NUMBA_CPU_NAME" \
  PYTHONDONTWRITEBYTECODE=1 \
  PYTHONUNBUFFERED=1 LANG=C.UTF-8 PATH=/usr/local/bin:/usr/bin:/bin \
  DRAGD_VCAN_BUS="$DRAGD_VCAN_BUS" DRAGD_VCAN_SIM_BUS="$DRAGD_VCAN_SIM_BUS" DRAGD_VCAN_LOOP_HZ="$DRAGD_VCAN_LOOP_HZ" \
  DRAGD_VCAN_PHYSICS_HZ="$DRAGD_VCAN_PHYSICS_HZ" DRAGD_VCAN_GUEST=1 \
  $B env "$@" </dev/null
rc=$?
echo "$rc" > "$SHARE/rc"
$B sync
say "suite exited with status $rc"
$B poweroff -f
