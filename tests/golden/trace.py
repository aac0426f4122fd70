"""Golden traces of the daemon's cycle: record (closed loop with the plant) and replay (open loop), compare.

A trace holds everything that went *into* the daemon — the configuration text, per cycle the frames that arrived
(TPDOs, EMCYs), the tick period and expirations, the operator's requests with their literal arguments — and what
came *out*: per cycle the command frames, the mode, the drive mode and the telemetry row. Replaying the inputs
through today's daemon must give the same outputs bit for bit: frames, modes and every telemetry value. Bit for bit
holds where the float arithmetic is the recording machine's (``arithmetic``: numpy's vectorised transcendental
functions and BLAS pick their kernels by CPU, and differ in the last bit between CPUs); elsewhere the telemetry is
compared within 1e-9 (relative and absolute) and the test says so.

Scenarios (``SCENARIOS``) script one run each: every mode (idle, hold, drag, track, replay, fault), the blends
between them, the start-up term and its latch, the soft-limit wall and speed cap, feedback holds and loss, missed
ticks and jittered periods, a protective stop, an EMCY, a drive fault, a refused enable, stop.
"""

from __future__ import annotations

import asyncio
import io
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


# ----------------------------------------------------------------------------------------------- scenarios


@dataclass
class Step:
    """What happens at one cycle: plant disturbances and/or an operator request."""

    plant: Callable[[Any], None] | None = None
    request: tuple[str, Callable[[Any], dict[str, Any]] | dict[str, Any]] | None = None


@dataclass
class Scenario:
    name: str
    base_config: str  # file under config/
    edit: Callable[[dict[str, Any]], None]
    cycles: int
    steps: dict[int, list[Step]] = field(default_factory=dict)
    missed: tuple[int, ...] = ()  # cycles whose tick came 2 periods after the previous one
    seed: int = 11

    def at(self, k: int, *steps: Step) -> Scenario:
        self.steps.setdefault(k, []).extend(steps)
        return self


def _hand(joint: int, nm: float) -> Step:
    def f(plant: Any) -> None:
        plant.hand_Nm[joint] = nm

    return Step(plant=f)


def _ramp(k0: int, k1: int, joint: int, nm0: float, nm1: float, sc: Scenario) -> None:
    for k in range(k0, k1, 10):
        sc.at(k, _hand(joint, nm0 + (nm1 - nm0) * (k - k0) / (k1 - k0)))


def _drop(joints: set[int], on: bool) -> Step:
    def f(plant: Any) -> None:
        if on:
            plant.drop |= joints
        else:
            plant.drop -= joints

    return Step(plant=f)


def _emcy(node: int, code: int) -> Step:
    return Step(plant=lambda p: p.emcy.append((node, code)))


def _drive_fault(joint: int) -> Step:
    return Step(plant=lambda p: p.drives[joint].fault())


def _refuse(joint: int, on: bool) -> Step:
    def f(p: Any) -> None:
        p.drives[joint].refuse_enable = on

    return Step(plant=f)


def _req(name: str, args: Callable[[Any], dict[str, Any]] | dict[str, Any] | None = None) -> Step:
    return Step(request=(name, args or {}))


def _track_args(ad: Any) -> dict[str, Any]:
    """A 2 s plain track from where the arm is: a smooth excursion on every joint and back."""
    q0 = ad.q.copy()
    t = np.linspace(0.0, 2.0, 21)
    bump = np.sin(np.pi * t / 2.0) ** 2
    amp = np.array([0.15, -0.10, 0.12, 0.2, -0.2, 0.25])
    return {"t_s": t.tolist(), "q_rad": (q0[None, :] + bump[:, None] * amp[None, :]).tolist()}


def _track_args_near_wall(ad: Any) -> dict[str, Any]:
    """The same track with joint 6 (next to its 0.35 rad wall after the drag) kept inside its position limits: a
    trajectory that leaves them is refused before motion (issue 12's validation)."""
    args = _track_args(ad)
    q0 = ad.q.copy()
    q = np.asarray(args["q_rad"])
    q[:, 5] = q0[5] + (q[:, 5] - q0[5]) * 0.5
    args["q_rad"] = q.tolist()
    return args


def _replay_args(ad: Any) -> dict[str, Any]:
    """A replay-like table (velocity and feed-forward tables, a repeated body) from where the arm is."""
    dt = 1e-3
    q0 = ad.q.copy()
    tt = np.arange(0.0, 1.6 + dt / 2, dt)
    x = np.clip(tt / 1.6, 0.0, 1.0)
    shape = np.sin(2 * np.pi * x) * np.sin(np.pi * x)
    amp = np.array([0.10, 0.08, -0.06, 0.15, 0.12, -0.2])
    q = q0[None, :] + shape[:, None] * amp[None, :]
    dq = np.gradient(q, dt, axis=0)
    ff = 0.5 * np.gradient(dq, dt, axis=0) * np.array([0.8, 1.0, 0.4, 0.05, 0.05, 0.02])
    return {"q": q.tolist(), "dq": dq.tolist(), "ff_Nm": ff.tolist(), "body_row": 200, "speed": 0.8, "cycles": 2}


def _edit_default(d: dict[str, Any]) -> None:
    d["joints"][5]["position_limits_rad"] = [-0.35, 0.35]  # a wall the hand reaches
    d["joints"][4]["velocity_limit_rad_s"] = 0.4  # a speed cap the hand exceeds


def scenario_default() -> Scenario:
    sc = Scenario("default", "default.yaml", _edit_default, 15000, missed=(2300, 2301, 5200, 7700))
    sc.at(30, _req("start")).at(300, _req("mode", {"mode": "drag"}))
    _ramp(500, 1300, 0, 0.0, 8.0, sc)
    _ramp(600, 1300, 1, 0.0, 5.0, sc)
    sc.at(1500, _hand(0, 0.0), _hand(1, 0.0))
    sc.at(2000, _drop({2}, True)).at(2015, _drop({2}, False))
    sc.at(2400, _hand(5, 4.0)).at(2900, _hand(5, 0.0))  # joint 6 into its wall
    sc.at(3000, _hand(4, 6.0)).at(3400, _hand(4, 0.0))  # joint 5 beyond its speed cap
    sc.at(3600, _req("mode", {"mode": "hold"}))
    sc.at(4000, _req("track", _track_args))
    sc.at(6500, _req("replay", _replay_args))
    sc.at(7000, _req("pause")).at(7700, _req("resume")).at(8000, _req("speed", {"speed": 0.5}))
    sc.at(8700, _req("track_stop"))
    sc.at(9300, _req("track", _track_args_near_wall))
    sc.at(9500, _hand(1, -60.0)).at(9800, _hand(1, 0.0))  # a blocked shoulder: tracking-error stop
    sc.at(10500, _emcy(2, 0x2310))
    sc.at(10700, _req("start"))
    sc.at(11200, _drive_fault(4))
    sc.at(11400, _req("start")).at(11800, _req("mode", {"mode": "drag"}))
    sc.at(12000, _req("stop"))
    sc.at(12500, _refuse(2, True), _req("start"))
    sc.at(13700, _refuse(2, False), _req("start"))
    sc.at(14000, _req("mode", {"mode": "drag"}))
    sc.at(14300, _drop({0}, True))
    return sc


def _edit_effects(d: dict[str, Any]) -> None:
    d["law"]["back_emf"] = True
    for j in d["joints"]:
        j["back_emf"] = {"constant_V_s_per_rad": 0.002, "resistance_ohm": 0.8}
    d["joints"][0]["effects"] = {"position_periodic": [{"cycles_per_rev": 6, "sin_A": 0.05, "cos_A": -0.02}],
                                 "current_offset_A": 0.03, "load_friction_per_Nm": 0.002}
    d["joints"][1]["effects"] = {"temperature_drift": {"friction_change": 0.1, "time_constant_s": 2.0},
                                 "back_emf": {"A_s_per_rad": 0.05, "knee_rad_s": 0.1}}
    d["payload"] = {"mass_kg": 0.5, "com_m": [0.0, 0.0, 0.05]}


def scenario_effects() -> Scenario:
    sc = Scenario("effects", "default.yaml", _edit_effects, 4000, seed=12)
    sc.at(20, _req("start")).at(250, _req("mode", {"mode": "drag"}))
    _ramp(400, 1200, 0, 0.0, 9.0, sc)
    _ramp(400, 1200, 3, 0.0, 3.0, sc)
    sc.at(1600, _hand(0, 0.0), _hand(3, 0.0))
    sc.at(3000, _req("mode", {"mode": "hold"})).at(3600, _req("stop"))
    return sc


def _edit_compact(d: dict[str, Any]) -> None:
    pass


def scenario_compact() -> Scenario:
    sc = Scenario("compact", "two_buses.yaml", _edit_compact, 4000, missed=(1800,), seed=13)
    sc.at(20, _req("start")).at(250, _req("mode", {"mode": "drag"}))
    _ramp(400, 1200, 1, 0.0, 6.0, sc)
    sc.at(1500, _hand(1, 0.0))
    sc.at(2000, _drop({4}, True)).at(2012, _drop({4}, False))
    sc.at(3000, _req("stop"))
    return sc


SCENARIOS: dict[str, Callable[[], Scenario]] = {"default": scenario_default, "effects": scenario_effects,
                                                "compact": scenario_compact}


def trace_path(name: str) -> Path:
    return HERE / f"{name}.npz"


LIVE = ("lockstep",)  # traces recorded from the real processes (golden/live.py), not from a scenario here


def arithmetic() -> str:
    """A fingerprint of this machine's float arithmetic as the cycle uses it (none of dragd's code): numpy's
    transcendental ufuncs, small BLAS products and a least-squares solve, Pinocchio's gravity, and numba's compiled
    arithmetic, on fixed inputs. Equal fingerprints: a replay must match a recording bit for bit."""
    import hashlib

    import numba
    import pinocchio as pin

    rng = np.random.default_rng(20261127)
    x = rng.uniform(-3.0, 3.0, 4096)
    a, b = rng.normal(size=(6, 6)), rng.normal(size=(6, 10))
    parts = [np.exp(x), np.log1p(np.abs(x)), np.sin(x), np.cos(x), np.tanh(x), np.arctan2(x, x[::-1]),
             np.sqrt(np.abs(x)), np.power(np.abs(x), 0.7), a @ b, a.dot(b[:, 0]),
             np.linalg.lstsq(b.T, x[:10], rcond=None)[0]]
    model = pin.buildSampleModelManipulator()
    data = model.createData()
    for k in range(8):
        q = np.ascontiguousarray(x[model.nq * k:model.nq * (k + 1)])
        parts.append(np.array(pin.computeGeneralizedGravity(model, data, q)))

    @numba.njit(cache=False)
    def mix(v: np.ndarray) -> np.ndarray:  # (what the cycle's kernels do: products, sums, rint, tanh, sqrt)
        out = np.empty_like(v)
        acc = 0.0
        for i in range(v.shape[0]):
            acc = acc * 0.999 + v[i] * 1.0001
            out[i] = np.rint(acc * 1000.0) + np.tanh(v[i]) * np.sqrt(abs(acc)) + np.exp(-abs(v[i]))
        return out

    parts.append(mix(x))
    h = hashlib.sha256()
    for p in parts:
        h.update(np.ascontiguousarray(p, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------------------------- files


def config_text(sc: Scenario) -> str:
    data = yaml.safe_load((REPO / "config" / sc.base_config).read_text())
    data["robot"]["urdf"] = "seed_cobot"
    sc.edit(data)
    return yaml.safe_dump(data, sort_keys=False)


def load_config_text(text: str, where: Path) -> Any:
    from dragd.config import load_config

    where.mkdir(parents=True, exist_ok=True)
    path = where / "golden.yaml"
    path.write_text(text)
    return load_config(path)


def _periods(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(sc.seed)
    period = 1000.0 + rng.normal(0.0, 25.0, sc.cycles)
    period[rng.integers(0, sc.cycles, sc.cycles // 200)] += 400.0  # occasional late ticks
    exp = np.ones(sc.cycles, dtype=np.int64)
    for k in sc.missed:
        exp[k] = 2
        period[k] = 2000.0 + rng.normal(0.0, 25.0)
    return np.round(period, 3), exp


def _pack_frames(per_cycle: list[list[tuple[str, int, bytes]]], buses: list[str]) -> dict[str, np.ndarray]:
    cyc, bus, cob, ln, data = [], [], [], [], []
    for k, frames in enumerate(per_cycle):
        for b, c, d in frames:
            cyc.append(k)
            bus.append(buses.index(b))
            cob.append(c)
            ln.append(len(d))
            data.append(np.frombuffer(d.ljust(64, b"\0"), dtype=np.uint8))
    return {"cycle": np.array(cyc, dtype=np.int32), "bus": np.array(bus, dtype=np.int8),
            "cob": np.array(cob, dtype=np.int32), "len": np.array(ln, dtype=np.int8),
            "data": np.array(data, dtype=np.uint8).reshape(-1, 64)}


def _unpack_frames(z: Any, prefix: str, cycles: int, buses: list[str]) -> list[list[tuple[str, int, bytes]]]:
    out: list[list[tuple[str, int, bytes]]] = [[] for _ in range(cycles)]
    for k, b, c, n, d in zip(z[prefix + "cycle"], z[prefix + "bus"], z[prefix + "cob"], z[prefix + "len"],
                             z[prefix + "data"], strict=True):
        out[int(k)].append((buses[int(b)], int(c), bytes(d[: int(n)])))
    return out


# ----------------------------------------------------------------------------------------------- record / replay


async def _record(sc: Scenario, workdir: Path) -> dict[str, Any]:
    from golden.adapter import DaemonAdapter
    from golden.plant import Plant

    text = config_text(sc)
    cfg = _guard_off(load_config_text(text, workdir), sc.name)  # (recorded as it is replayed)
    ad = DaemonAdapter(cfg)
    buses = list(ad.d.layouts)
    plant = Plant(ad.d.layouts, [j.node_id for j in cfg.joints], [j.encoder_offset_counts for j in cfg.joints],
                  seed=sc.seed)
    period, exp = _periods(sc)
    frames_in: list[list[tuple[str, int, bytes]]] = []
    frames_out: list[list[tuple[str, int, bytes]]] = []
    events: list[dict[str, Any]] = []
    rows: list[dict[str, np.ndarray]] = []
    mode = np.full(sc.cycles, -1, dtype=np.int8)
    drive_mode = np.zeros(sc.cycles, dtype=np.int8)
    computed = np.zeros(sc.cycles, dtype=bool)
    for k in range(sc.cycles):
        for _ in range(int(exp[k]) - 1):  # the missed tick: the arm moved on, nobody sampled it
            plant.step_1ms()
        for st in sc.steps.get(k, []):
            if st.plant is not None:
                st.plant(plant)
            if st.request is not None:
                name, args = st.request
                literal = args(ad) if callable(args) else dict(args)
                try:
                    await ad.request(name, literal)
                    err = None
                except ValueError as exc:
                    err = str(exc)
                events.append({"cycle": k, "request": name, "args": literal, "error": err})
        fin = plant.sync()
        frames_in.append(fin)
        res = await ad.cycle(fin, float(period[k]), int(exp[k]))
        if res["computed"]:
            computed[k] = True
            mode[k] = res["mode"]
            drive_mode[k] = res["drive_mode"]
            rows.append(res["telemetry"])
            for _b, cob, data in res["frames"]:
                plant.receive(cob, data)
            frames_out.append(res["frames"])
            for dm in ad.drive_mode_events:
                for dr in plant.drives:
                    dr.mode = dm
            ad.drive_mode_events.clear()
        else:
            frames_out.append([])
        plant.step_1ms()
    tele = {f"tele_{k}": np.stack([r[k] for r in rows]) for k in rows[0]}
    return {"config": text, "arithmetic": arithmetic(), "buses": json.dumps(buses), "events": json.dumps(events),
            "period_us": period,
            "expirations": exp, "mode": mode, "drive_mode": drive_mode, "computed": computed,
            "faults": json.dumps([f["text"] for f in ad.faults]), "log": json.dumps(ad.log),
            **{f"in_{k}": v for k, v in _pack_frames(frames_in, buses).items()},
            **{f"out_{k}": v for k, v in _pack_frames(frames_out, buses).items()}, **tele}


def record(name: str, workdir: Path) -> Path:
    if name in LIVE:
        from golden.live import record_lockstep

        data = record_lockstep(workdir / name)
    else:
        data = asyncio.run(_record(SCENARIOS[name](), workdir))
    path = trace_path(name)
    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: (np.array(v) if isinstance(v, str) else v) for k, v in data.items()})
    path.write_bytes(buf.getvalue())
    return path


@dataclass
class Replay:
    """Today's daemon fed a recorded trace: outputs next to the recorded ones."""

    name: str
    cycles: int
    computed: np.ndarray
    mode: tuple[np.ndarray, np.ndarray]
    drive_mode: tuple[np.ndarray, np.ndarray]
    frames: tuple[list[list[tuple[str, int, bytes]]], list[list[tuple[str, int, bytes]]]]
    telemetry: dict[str, tuple[np.ndarray, np.ndarray]]
    events: tuple[list[str | None], list[str | None]]
    faults: tuple[list[str], list[str]]
    exact: bool = True  # the recording machine's float arithmetic (``arithmetic``): bit for bit is the verdict


# Traces replayed with the runaway guard off, and why. The others run with it on (all were recorded before it
# existed): their hands never trip it, so their outputs stay bit for bit (a false trip would change the mode).
GUARD_OFF = {
    "compact": "its recording's plant does not apply the compact layout's current command (the recorded arm falls "
               "at 3.4 rad/s in drag with ~0 A measured; the real sim holds it: tests/test_daemon_buses.py); the guard "
               "rightly holds that fall at cycle 529, which the pre-guard recording cannot show",
}


def _written_digits(n: int) -> dict[str, int]:
    """The significant digits each float field of the cycle row is written with (dragd/telemetry/layout.py)."""
    from dragd.telemetry.layout import RowLayout
    from dragd.telemetry.schema import cycle_layout

    return {c.name: c.digits for c in RowLayout(cycle_layout(n)).columns if c.kind == "float"}


def _guard_off(cfg: Any, name: str) -> Any:
    if name not in GUARD_OFF:
        return cfg
    g = cfg.safety.guard.model_copy(update={"runaway": False})
    return cfg.model_copy(update={"safety": cfg.safety.model_copy(update={"guard": g})})


async def _replay(z: Any, workdir: Path, name: str = "") -> Replay:
    from golden.adapter import DaemonAdapter

    cfg = _guard_off(load_config_text(str(z["config"]), workdir), name)
    ad = DaemonAdapter(cfg)
    buses = json.loads(str(z["buses"]))
    period, exp = z["period_us"], z["expirations"]
    cycles = int(period.shape[0])
    frames_in = _unpack_frames(z, "in_", cycles, buses)
    frames_rec = _unpack_frames(z, "out_", cycles, buses)
    by_cycle: dict[int, list[dict[str, Any]]] = {}
    for ev in json.loads(str(z["events"])):
        by_cycle.setdefault(ev["cycle"], []).append(ev)
    mode = np.full(cycles, -1, dtype=np.int8)
    drive_mode = np.zeros(cycles, dtype=np.int8)
    computed = np.zeros(cycles, dtype=bool)
    frames_out: list[list[tuple[str, int, bytes]]] = []
    rows: list[dict[str, np.ndarray]] = []
    errors_rec, errors_now = [], []
    for k in range(cycles):
        for ev in by_cycle.get(k, []):
            try:
                await ad.request(ev["request"], ev["args"])
                err = None
            except ValueError as exc:
                err = str(exc)
            errors_rec.append(ev["error"])
            errors_now.append(err)
        res = await ad.cycle(frames_in[k], float(period[k]), int(exp[k]))
        if res["computed"]:
            computed[k] = True
            mode[k] = res["mode"]
            drive_mode[k] = res["drive_mode"]
            rows.append(res["telemetry"])
            frames_out.append(res["frames"])
        else:
            frames_out.append([])
    tele = {}
    digits = _written_digits(ad.n) if "telemetry_as_written" in z.files else {}
    for key in z.files:
        if key.startswith("tele_"):
            name = key[5:]
            now = np.stack([r[name] for r in rows]) if rows and name in rows[0] else None
            if now is not None and name in digits:  # (a recording from a telemetry file: its rows as written)
                now = np.vectorize(lambda x, d=digits[name]: float(f"%.{d}g" % x))(now)
            tele[name] = (z[key], now)
    exact = "arithmetic" in z.files and str(z["arithmetic"]) == arithmetic()
    return Replay(str(z["config"])[:0] or "trace", cycles, computed, (z["mode"], mode), (z["drive_mode"], drive_mode),
                  (frames_rec, frames_out), tele, (errors_rec, errors_now),
                  (json.loads(str(z["faults"])), [f["text"] for f in ad.faults]), exact)


def replay(name: str, workdir: Path) -> Replay:
    with np.load(trace_path(name), allow_pickle=False) as z:
        return asyncio.run(_replay(z, workdir, name))


def compare(r: Replay, rtol: float | None = None, atol: float | None = None) -> list[str]:
    """Every difference between the recorded outputs and today's, as readable lines (empty: identical). The
    telemetry bit for bit where the arithmetic is the recording's (``r.exact``), else within 1e-9."""
    if rtol is None:
        rtol = 0.0 if r.exact else 1e-9
    if atol is None:
        atol = 0.0 if r.exact else 1e-9
    problems: list[str] = []
    for what, (rec, now) in (("mode", r.mode), ("drive mode", r.drive_mode)):
        bad = np.flatnonzero(rec != now)
        if bad.size:
            k = int(bad[0])
            problems.append(f"{what} differs in {bad.size} cycles, first at cycle {k}: recorded {rec[k]}, now {now[k]}")
    rec_f, now_f = r.frames
    bad_frames = [k for k in range(r.cycles) if rec_f[k] != now_f[k]]
    if bad_frames:
        k = bad_frames[0]
        problems.append(f"command frames differ in {len(bad_frames)} cycles, first at cycle {k}:\n"
                        f"  recorded {[(b, hex(c), d.hex()) for b, c, d in rec_f[k]]}\n"
                        f"  now      {[(b, hex(c), d.hex()) for b, c, d in now_f[k]]}")
    for name, (rec, now) in r.telemetry.items():
        if now is None:
            problems.append(f"telemetry field {name} is gone")
            continue
        if rec.shape != now.shape:
            problems.append(f"telemetry field {name}: shape {rec.shape} now {now.shape}")
            continue
        close = (np.isclose(rec, now, rtol=rtol, atol=atol, equal_nan=True) if rtol or atol
                 else (rec == now) | (np.isnan(rec) & np.isnan(now)))
        if not close.all():
            k = int(np.flatnonzero(~close.all(axis=1))[0])
            problems.append(f"telemetry {name} differs in {int((~close.all(axis=1)).sum())} rows, first row {k}: "
                            f"recorded {rec[k].tolist()}, now {now[k].tolist()}")
    if r.events[0] != r.events[1]:
        problems.append(f"request outcomes differ: recorded {r.events[0]}, now {r.events[1]}")
    if r.faults[0] != r.faults[1]:
        problems.append(f"faults differ: recorded {r.faults[0]}, now {r.faults[1]}")
    return problems


def coverage(name: str) -> dict[str, Any]:
    """What a trace exercises: cycles per mode, fault texts, request outcomes (for the test's sanity checks)."""
    with np.load(trace_path(name), allow_pickle=False) as z:
        mode = z["mode"]
        return {"modes": {int(m): int((mode == m).sum()) for m in np.unique(mode) if m >= 0},
                "faults": json.loads(str(z["faults"])), "events": json.loads(str(z["events"])),
                "drive_modes": sorted({int(x) for x in np.unique(z["drive_mode"])}),
                "missed": int((z["expirations"] > 1).sum())}
