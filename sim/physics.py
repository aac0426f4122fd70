"""Arm physics of the simulated robot: rigid-body dynamics (Pinocchio ABA) plus the drive train's truth.

Per fixed step (``truth.physics_rate_Hz``, >= 4 kHz), reading each joint's :class:`~sim.axis.AxisIO`:

* current loop: first-order lag of the motor current towards ``current_demand_A`` (zero with the power stage off);
  joint torque = true K_t · I; the Hall reading adds offset, noise and quantisation (``current_measured_A``);
* friction: direction-asymmetric Stribeck curve plus viscous slope, with stick–slip as a constraint (Karnopp-like,
  exact): a joint at rest gets exactly the torque that keeps it at rest — solved for all stuck joints together
  through M⁻¹ — until that torque exceeds its static level; a sliding joint whose velocity reverses sticks.
  No chatter, no drift: a stuck joint's velocity is exactly zero;
* brakes: an engaged brake adds its holding torque to the joint's static and sliding friction (it locks the
  joint and slips above the holding torque);
* hard stops: spring–damper beyond each limit, never pulling;
* hidden effects (off by default): torque ripple, load-dependent friction, thermal friction drift, Hall offset,
  backlash (a separate rotor inertia coupled to the output through a dead zone and the gear stiffness; the joint's
  friction split between rotor and output by ``output_friction_fraction``, the brake on the rotor), a flange
  payload (``truth.payload``, in the Pinocchio model), back-EMF voltage headroom (the winding current falls short
  of the regulated reading above a knee speed), a time-based friction warm-up drift;
* semi-implicit Euler: v += a·dt, then q += v·dt.

Rotor inertia × gear² enters the Pinocchio model as armature (joints without backlash), so ABA includes it.
Per-joint scalar work runs on Python floats (cheaper than numpy calls for six joints); Pinocchio gets numpy.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pinocchio as pin

from sim.axis import AxisIO
from sim.kernels import hold_kernel
from sim.truth import Truth, TruthError

if TYPE_CHECKING:
    from dragd.model import RobotModel

NOISE_BLOCK_ROWS = 256
STABILITY_MARGIN = 0.5  # max ω·dt (springs) and c·dt/I (dampers) accepted at the truth's step


class ExternalTorque(Protocol):
    """Writes the operator's joint torques each step (see :class:`sim.operator.Operator`)."""

    def apply(self, t_s: float, q_rad: np.ndarray, dq_rad_s: np.ndarray, out_Nm: np.ndarray) -> None: ...


def _solve_spd(a: list[list[float]], idx: list[int], rhs: list[float]) -> list[float]:
    """Solve A[idx, idx]·x = rhs for a small symmetric positive-definite A (Gaussian elimination, no pivoting)."""
    m = len(idx)
    if m == 1:
        return [rhs[0] / a[idx[0]][idx[0]]]
    rows = [[a[i][j] for j in idx] + [rhs[r]] for r, i in enumerate(idx)]
    for c in range(m):
        piv = rows[c]
        inv = 1.0 / piv[c]
        for r in range(c + 1, m):
            row = rows[r]
            f = row[c] * inv
            if f != 0.0:
                for k in range(c, m + 1):
                    row[k] -= f * piv[k]
    x = [0.0] * m
    for c in range(m - 1, -1, -1):
        row = rows[c]
        s = row[m]
        for k in range(c + 1, m):
            s -= row[k] * x[k]
        x[c] = s / row[c]
    return x



def hold_stuck(minv: list[list[float]], a: list[float], stuck: list[bool], lim_pos: list[float],
               lim_neg: list[float], fric: list[float], dirs: list[float]) -> None:
    """Hold the stuck DOFs by stiction: ``a`` (free accelerations, in place) gets the holding torques' effect.

    A stuck DOF whose holding torque exceeds its static level in the direction it would move breaks away (the worst
    first, the rest re-solved): it is marked sliding in ``stuck``/``dirs`` with its static level as friction.
    ``fric`` gets every stuck DOF's holding torque and each released one's friction; the held DOFs' ``a`` is 0.
    The reference of sim/kernels.py's compiled kernel (the same operations in the same order).
    """
    nf = len(a)
    S = [k for k in range(nf) if stuck[k]]
    lam: list[float] = []
    while S:
        lam = _solve_spd(minv, S, [-a[k] for k in S])
        worst, worst_excess = -1, 0.0
        for i, k in enumerate(S):
            lk = lam[i]
            excess = lk - lim_neg[k] if lk > 0.0 else -lk - lim_pos[k]
            if excess > worst_excess:
                worst, worst_excess = i, excess
        if worst < 0:
            break
        k = S.pop(worst)
        d = -1.0 if lam[worst] > 0.0 else 1.0  # it moves against the torque that would have held it
        f = -d * (lim_pos[k] if d > 0.0 else lim_neg[k])
        for i in range(nf):
            a[i] += minv[i][k] * f
        fric[k] = f
        stuck[k] = False
        dirs[k] = d
        lam = []
    for i, k in enumerate(S):
        lk = lam[i]
        fric[k] = lk
        for r in range(nf):
            a[r] += minv[r][k] * lk
    for k in S:
        a[k] = 0.0

class ArmPhysics:
    """The simulated arm: call :meth:`step` once per physics step after the drives' ``update``.

    Truth state: ``q_rad``, ``dq_rad_s`` (numpy views, current), ``tau_ext_Nm`` (numpy, the operator's — write
    it directly when no ``operator`` is set), ``current_A``, ``current_measured_A``, ``tau_motor_Nm``,
    ``tau_friction_Nm``, ``tau_stop_Nm``, ``stuck``, ``brakes``, ``temperature_C`` (fresh arrays), ``t_s``, ``steps``.
    ``compiled=False`` holds stuck DOFs with the Python reference instead of the compiled kernel (sim/kernels.py).
    """

    def __init__(self, truth: Truth, model: RobotModel | pin.Model, axes: list[AxisIO], *,
                 compiled: bool = True) -> None:
        src: pin.Model = getattr(model, "model", model)
        names = tuple(src.names[1:])
        truth.check_model(names)
        n = src.nv
        if len(axes) != n:
            raise ValueError(f"ArmPhysics: expected {n} AxisIO (one per joint), got {len(axes)}")
        self.truth = truth
        self.joint_names = names
        self.axes = axes
        self.n = n
        self.dt_s = truth.dt_s
        joints = truth.joints

        # private model copy with the truth's gravity and armature (the caller's model stays constant)
        self.model = pin.Model(src)
        self.model.gravity.linear = np.asarray(truth.gravity_m_s2, dtype=float)
        if truth.payload is not None and truth.payload.mass_kg > 0:  # hidden: a flange load the URDF lacks
            body = self.model.njoints - 1
            self.model.inertias[body] = self.model.inertias[body] + pin.Inertia(
                truth.payload.mass_kg, np.asarray(truth.payload.com_m, dtype=float), np.zeros((3, 3)))
        self._bj = [i for i, j in enumerate(joints) if j.hidden.backlash_rad > 0]  # joints with a separate rotor
        self.nb = nb = len(self._bj)
        self.nf = nf = n + nb
        armature = [j.armature_kgm2 for j in joints]
        self.model.armature[:] = [0.0 if i in self._bj else a for i, a in enumerate(armature)]
        self.data = self.model.createData()

        # DOFs: the n outputs, then one rotor per backlash joint (rotor angle in joint units)
        self._fdof = list(range(n))  # the DOF carrying each joint's motor torque, friction and brake
        for r, i in enumerate(self._bj):
            self._fdof[i] = n + r
        # friction rows (joint, DOF, share): a backlash joint's friction is split between its rotor and its output
        # (gear input and motor bearings vs output bearing and seals, ``hidden.output_friction_fraction``)
        self._frows: list[tuple[int, int, float]] = []
        for i, k in enumerate(self._fdof):
            share = joints[i].hidden.output_friction_fraction if k != i else 0.0
            self._frows.append((i, k, 1.0 - share))
            if share > 0.0:
                self._frows.append((i, i, share))
        self._dof_joint = [-1] * nf  # joint of each friction DOF (-1: a frictionless backlash output)
        for i, k, _share in self._frows:
            self._dof_joint[k] = i
        self._rotor_inertia = [armature[i] for i in self._bj]
        self._x = np.zeros(nf)
        self._v = np.zeros(nf)
        self.q_rad = self._x[:n]
        self.dq_rad_s = self._v[:n]
        self._xs = [0.0] * nf
        self._vs = [0.0] * nf

        # drive train
        self._kt = [j.torque_constant_Nm_per_A for j in joints]
        self._alpha = [1.0 - math.exp(-self.dt_s / j.current_loop_time_constant_s) for j in joints]
        self._offset = [j.hidden.current_offset_A for j in joints]
        self._noise_std = np.array([j.current_noise_std_A for j in joints])
        self._quantum = [j.current_quantum_A for j in joints]
        self._rng = np.random.default_rng(truth.noise_seed)
        self._noise: list[float] = []  # flat rows of n Hall noise samples
        self._noise_pos = 0

        # friction truth per joint (it acts on the joint's friction DOF); negative-direction levels as magnitudes
        fr = [j.friction for j in joints]
        self._fc_pos = [f.coulomb_pos_Nm for f in fr]
        self._fc_neg = [-f.coulomb_neg_Nm for f in fr]
        self._fs_pos = [f.static_pos for f in fr]
        self._fs_neg = [-f.static_neg for f in fr]
        self._vs_inv = [1.0 / f.stribeck_velocity_rad_s for f in fr]
        self._delta = [f.stribeck_exponent for f in fr]
        self._visc_pos = [f.viscous_pos_Nm_s_per_rad for f in fr]
        self._visc_neg = [f.viscous_neg_Nm_s_per_rad for f in fr]
        self._hold = [j.brake_holding_torque_Nm for j in joints]
        self._load_coef = [j.hidden.load_friction_per_Nm for j in joints]
        self._load_on = any(c > 0 for c in self._load_coef)

        # hard stops (outputs)
        self._lower = [j.hard_stops.lower_rad for j in joints]
        self._upper = [j.hard_stops.upper_rad for j in joints]
        self._k_stop = [j.hard_stops.stiffness_Nm_per_rad for j in joints]
        self._d_stop = [j.hard_stops.damping_Nm_s_per_rad for j in joints]

        # ripple rows (friction DOF, amplitude, cycles per joint-unit radian of that DOF, phase)
        self._ripple = [(self._fdof[i], r.amplitude_Nm,
                         r.cycles_per_rev * (j.gear_ratio if r.reference == "motor" else 1.0), r.phase_rad)
                        for i, j in enumerate(joints) for r in j.hidden.ripple if r.amplitude_Nm > 0]

        # backlash coupling rows (output DOF, rotor DOF, half gap, stiffness, damping); the damping is the given
        # fraction of critical for the output/rotor pair at the initial pose
        self._gear: list[tuple[int, int, float, float, float]] = []

        # thermal rows (joint, ambient, reference, capacity, resistance, winding ohm, coefficient per K)
        self._thermal = [(i, t.ambient_C, t.reference_C, t.heat_capacity_J_per_K, t.thermal_resistance_K_per_W,
                          t.winding_resistance_ohm, t.friction_coefficient_per_K)
                         for i, j in enumerate(joints) if (t := j.hidden.thermal) is not None]
        self._temp = [25.0] * n
        for i, j in enumerate(joints):
            if (t := j.hidden.thermal) is not None:
                self._temp[i] = t.initial_C if t.initial_C is not None else t.ambient_C
        self._scale = [1.0] * n
        self._vscale = self._scale  # the viscous slope's scale: its own list only where a drift changes it apart
        # friction warm-up drift rows (joint, change, time constant, viscous change) and back-EMF headroom rows
        # (joint, A·s/rad, knee)
        self._drift = [(i, d.change, d.time_constant_s, d.viscous_change) for i, j in enumerate(joints)
                       if (d := j.hidden.friction_drift) is not None]
        if any(row[3] is not None for row in self._drift):
            self._vscale = [1.0] * n
        self._thermal_coef = {row[0]: (row[2], row[6]) for row in self._thermal}
        self._emf = [(i, b.A_s_per_rad, b.knee_rad_s) for i, j in enumerate(joints)
                     if (b := j.hidden.back_emf) is not None]

        # per-step signals
        self._demand = [0.0] * n
        self._on = [False] * n
        self._brakes = [True] * n
        self._cur = [0.0] * n
        self._meas = [0.0] * n
        self._tau_m = [0.0] * n
        self._tau_stop = [0.0] * n
        self._gravity = [0.0] * n
        self.tau_ext_Nm = np.zeros(n)  # operator's joint torques (written by the operator, or directly)
        self.operator: ExternalTorque | None = None

        # stick–slip bookkeeping (DOF space)
        self._stuck = [False] * nf
        self._dir = [0.0] * nf  # sliding direction (+1/−1); 0 while stuck or resting without friction
        self._sticky = [False] * nf  # friction or brake > 0: the DOF can stick
        self._fric = [0.0] * nf  # torque friction/brake exert on each DOF (stiction included)
        self._lim_pos = [0.0] * nf
        self._lim_neg = [0.0] * nf
        # the compiled holding kernel and its arrays (None: the Python reference, numba missing or not asked for)
        self._hold_kernel: Any = hold_kernel() if compiled else None
        minv0 = np.zeros((nf, nf))
        for r in range(nb):
            minv0[n + r, n + r] = 1.0 / self._rotor_inertia[r]
        self._hold_work = {"minv": minv0, "a": np.zeros(nf), "stuck": np.zeros(nf, dtype=np.bool_),
                           "lim_pos": np.zeros(nf), "lim_neg": np.zeros(nf), "fric": np.zeros(nf),
                           "dirs": np.zeros(nf), "idx": np.zeros(nf, dtype=np.int64),
                           "rows": np.zeros((nf, nf + 1)), "lam": np.zeros(nf)}

        self.t_s = 0.0
        self.steps = 0
        self.set_state(np.array([j.initial_position_rad for j in joints]))
        minv = self._inverse_inertia()
        for r, i in enumerate(self._bj):
            h = joints[i].hidden
            reduced = 1.0 / (minv[i][i] + minv[n + r][n + r])
            damping = 2.0 * h.gear_damping_ratio * math.sqrt(h.gear_stiffness_Nm_per_rad * reduced)
            self._gear.append((i, n + r, h.backlash_rad / 2, h.gear_stiffness_Nm_per_rad, damping))
        self._check_stability()

    # ------------------------------------------------------------------------------------------- state

    @property
    def current_A(self) -> np.ndarray:
        """Actual motor currents."""
        return np.array(self._cur)

    @property
    def current_measured_A(self) -> np.ndarray:
        return np.array(self._meas)

    @property
    def current_demand_A(self) -> np.ndarray:
        return np.array(self._demand)

    @property
    def tau_motor_Nm(self) -> np.ndarray:
        return np.array(self._tau_m)

    @property
    def tau_friction_Nm(self) -> np.ndarray:
        """Torque friction and brakes exert on each joint (rotor and output together for backlash joints)."""
        out = [0.0] * self.n
        for j, k, _share in self._frows:
            out[j] += self._fric[k]
        return np.array(out)

    @property
    def tau_stop_Nm(self) -> np.ndarray:
        return np.array(self._tau_stop)

    @property
    def stuck(self) -> np.ndarray:
        return np.array([self._stuck[k] for k in self._fdof])

    @property
    def brakes(self) -> np.ndarray:
        return np.array(self._brakes)

    @property
    def power_on(self) -> np.ndarray:
        return np.array(self._on)

    @property
    def temperature_C(self) -> np.ndarray:
        return np.array(self._temp)

    @property
    def rotor_rad(self) -> np.ndarray:
        """Rotor angles (joint units) of backlash joints, in joint order."""
        return self._x[self.n:].copy()

    def set_state(self, q_rad: np.ndarray, dq_rad_s: np.ndarray | None = None) -> None:
        """Teleport the arm (rotors follow with the gap centred); joints at zero velocity are stuck."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        if q.shape[0] != self.n or not np.all(np.isfinite(q)):
            raise ValueError(f"set_state: expected {self.n} finite joint positions, got {q.tolist()}")
        dq = np.zeros(self.n) if dq_rad_s is None else np.asarray(dq_rad_s, dtype=float).reshape(-1)
        xs = q.tolist() + [float(q[i]) for i in self._bj]
        vs = dq.tolist() + [float(dq[i]) for i in self._bj]
        self._xs[:] = xs
        self._vs[:] = vs
        self._x[:] = xs
        self._v[:] = vs
        for k in range(self.nf):
            self._stuck[k] = self._dof_joint[k] >= 0 and vs[k] == 0.0
            self._dir[k] = 0.0 if vs[k] == 0.0 else math.copysign(1.0, vs[k])
        self._cur[:] = [0.0] * self.n
        self._write_outputs()

    def snapshot(self) -> dict[str, Any]:
        """The truth state as plain lists (JSON-ready)."""
        return {
            "t": self.t_s,
            "steps": self.steps,
            "q_rad": self.q_rad.tolist(),
            "dq_rad_s": self.dq_rad_s.tolist(),
            "current_A": list(self._cur),
            "current_measured_A": list(self._meas),
            "current_demand_A": list(self._demand),
            "tau_motor_Nm": list(self._tau_m),
            "tau_ext_Nm": self.tau_ext_Nm.tolist(),
            "tau_friction_Nm": self.tau_friction_Nm.tolist(),
            "tau_stop_Nm": list(self._tau_stop),
            "stuck": self.stuck.tolist(),
            "brakes": list(self._brakes),
            "power_on": list(self._on),
            "temperature_C": list(self._temp),
            "rotor_rad": self.rotor_rad.tolist(),
        }

    def static_friction_Nm(self, joint: int, direction: int) -> float:
        """Breakaway level of one joint in a direction (+1/−1): friction with the present load term and thermal
        scale, plus the holding torque if the brake was engaged at the last step."""
        self._limits()
        lim = self._lim_pos if direction > 0 else self._lim_neg
        return sum(lim[k] for j, k, _share in self._frows if j == joint)

    # ------------------------------------------------------------------------------------------- step

    def step(self) -> None:
        """Advance one physics step."""
        n, nf, dt = self.n, self.nf, self.dt_s
        axes = self.axes
        demand, on, cur, tau_m = self._demand, self._on, self._cur, self._tau_m
        alpha, offset, kt = self._alpha, self._offset, self._kt
        for j, ax in enumerate(axes):
            demand[j] = ax.current_demand_A
            on[j] = ax.power_stage_on
            self._brakes[j] = ax.brake_engaged
            if on[j]:
                c = cur[j]
                c += alpha[j] * (demand[j] - offset[j] - c)  # the loop regulates the reading (offset included)
            else:
                c = 0.0
            cur[j] = c
            tau_m[j] = kt[j] * c
        for j, k_emf, knee in self._emf:  # voltage headroom: the winding gets less than the loop regulates
            v = self._vs[self._fdof[j]]
            over = (v if v >= 0.0 else -v) - knee
            if over > 0.0:
                tau_m[j] -= kt[j] * k_emf * math.copysign(over, v)

        if self.operator is not None:
            self.operator.apply(self.t_s, self.q_rad, self.dq_rad_s, self.tau_ext_Nm)
        F = self.tau_ext_Nm.tolist()
        if self.nb:
            F += [0.0] * self.nb
        xs, vs = self._xs, self._vs

        # hard stops: push out, never pull in
        lower, upper, ts = self._lower, self._upper, self._tau_stop
        for j in range(n):
            qj = xs[j]
            if qj < lower[j]:
                t = -self._k_stop[j] * (qj - lower[j]) - self._d_stop[j] * vs[j]
                ts[j] = t if t > 0.0 else 0.0
            elif qj > upper[j]:
                t = -self._k_stop[j] * (qj - upper[j]) - self._d_stop[j] * vs[j]
                ts[j] = t if t < 0.0 else 0.0
            else:
                ts[j] = 0.0
            F[j] += ts[j]
        fdof = self._fdof
        for j in range(n):
            F[fdof[j]] += tau_m[j]
        for k, amp, cyc, ph in self._ripple:
            F[k] += amp * math.sin(cyc * xs[k] + ph)
        for jo, kr, half, kg, dg in self._gear:
            gap = xs[kr] - xs[jo]
            e = gap - half if gap > half else (gap + half if gap < -half else 0.0)
            if e != 0.0:
                t = kg * e + dg * (vs[kr] - vs[jo])
                t = (t if t > 0.0 else 0.0) if e > 0.0 else (t if t < 0.0 else 0.0)  # teeth push, never pull
                F[jo] += t
                F[kr] -= t
        if self._load_on:
            self._gravity[:] = pin.computeGeneralizedGravity(self.model, self.data, self.q_rad).tolist()
        self._limits()
        n_stuck = self._sliding_friction(F)
        if n_stuck == 0:
            a = self._free_acceleration(F)
        else:
            a = self._constrained_acceleration(F, n_stuck)

        # semi-implicit Euler; a sliding DOF whose velocity reverses sticks (friction would have stopped it)
        stuck, dirs, sticky = self._stuck, self._dir, self._sticky
        for k in range(nf):
            v = vs[k] + a[k] * dt
            if not stuck[k]:
                d = dirs[k]
                if sticky[k] and v * d <= 0.0:
                    v = 0.0
                    stuck[k] = True
                    dirs[k] = 0.0
                elif v > 0.0:
                    dirs[k] = 1.0
                elif v < 0.0:
                    dirs[k] = -1.0
            vs[k] = v
            xs[k] += v * dt
        self._x[:] = xs
        self._v[:] = vs

        if self._thermal:
            self._heat()
        self.steps += 1
        self.t_s = self.steps * dt
        self._write_outputs()

    # ------------------------------------------------------------------------------------------- parts

    def _limits(self) -> None:
        """Breakaway level per DOF and direction: static × thermal scale + load term + engaged brake."""
        lp, ln, sticky = self._lim_pos, self._lim_neg, self._sticky
        brakes, hold, scale = self._brakes, self._hold, self._scale
        for j, _amb, ref, _cap, _res, _rw, coef in self._thermal:
            scale[j] = 1.0 + coef * (self._temp[j] - ref)
        vscale = self._vscale
        if vscale is not scale:
            vscale[:] = scale
        for j, change, tau, vchange in self._drift:
            th = self._thermal_coef.get(j)
            base = 1.0 + th[1] * (self._temp[j] - th[0]) if th is not None else 1.0
            g = 1.0 - math.exp(-self.t_s / tau)
            scale[j] = base * (1.0 + change * g)
            if vscale is not scale:
                vscale[j] = base * (1.0 + (change if vchange is None else vchange) * g)
        load = self._load_on
        fdof = self._fdof
        for j, k, share in self._frows:
            extra = self._load_coef[j] * abs(self._gravity[j]) * share if load else 0.0
            if brakes[j] and k == fdof[j]:  # the brake holds the motor shaft
                extra += hold[j]
            s = scale[j] * share
            p = self._fs_pos[j] * s + extra
            m = self._fs_neg[j] * s + extra
            lp[k] = p
            ln[k] = m
            sticky[k] = p + m > 0.0

    def _sliding_friction(self, F: list[float]) -> int:
        """Add kinetic friction (Stribeck, viscous, slipping brake) of sliding DOFs to F; return the stuck count."""
        stuck, dirs, vs, fric = self._stuck, self._dir, self._vs, self._fric
        n_stuck = 0
        fdof = self._fdof
        for j, k, share in self._frows:
            if stuck[k]:
                fric[k] = 0.0
                n_stuck += 1
                continue
            d = dirs[k]
            v = vs[k]
            s = self._scale[j] * share
            sv = self._vscale[j] * share
            extra = self._load_coef[j] * abs(self._gravity[j]) * share if self._load_on else 0.0
            if self._brakes[j] and k == fdof[j]:
                extra += self._hold[j]
            if d > 0.0:
                fc = self._fc_pos[j] * s + extra
                lim = self._lim_pos[k]
                visc = self._visc_pos[j] * sv
            elif d < 0.0:
                fc = self._fc_neg[j] * s + extra
                lim = self._lim_neg[k]
                visc = self._visc_neg[j] * sv
            else:  # at rest without friction (cannot stick): only a viscous term, which is zero here
                fric[k] = 0.0
                continue
            av = v if v >= 0.0 else -v
            strib = math.exp(-((av * self._vs_inv[j]) ** self._delta[j])) if av > 0.0 else 1.0
            f = -(d * (fc + (lim - fc) * strib) + visc * v)
            fric[k] = f
            F[k] += f
        return n_stuck

    def _free_acceleration(self, F: list[float]) -> list[float]:
        """Unconstrained accelerations: ABA for the outputs (armature included), τ/J for separate rotors."""
        n = self.n
        a = pin.aba(self.model, self.data, self.q_rad, self.dq_rad_s, np.array(F[:n])).tolist()
        for r in range(self.nb):
            a.append(F[n + r] / self._rotor_inertia[r])
        return a

    def _inverse_inertia(self) -> list[list[float]]:
        """M⁻¹ of all DOFs (outputs from Pinocchio's ABA-based algorithm, rotors block-diagonal)."""
        minv = pin.computeMinverse(self.model, self.data, self.q_rad).tolist()
        if self.nb:
            for row in minv:
                row.extend([0.0] * self.nb)
            for r in range(self.nb):
                row = [0.0] * self.nf
                row[self.n + r] = 1.0 / self._rotor_inertia[r]
                minv.append(row)
        return minv

    def _constrained_acceleration(self, F: list[float], n_stuck: int) -> list[float]:
        """Accelerations with stuck DOFs held by stiction (their friction torque solved exactly).

        A stuck DOF whose required holding torque exceeds its static level in the direction it would move breaks
        away: it leaves the stuck set and gets that static level as sliding friction (the Stribeck curve at v = 0).
        The worst excess is released first and the rest re-solved, since releasing one changes the others' need.
        """
        stuck, fric, lp, ln, dirs = self._stuck, self._fric, self._lim_pos, self._lim_neg, self._dir
        nf = self.nf
        if n_stuck == nf:
            # everything at rest: the holding torque is G(q) − F without any inertia, unless something breaks away
            g = pin.computeGeneralizedGravity(self.model, self.data, self.q_rad).tolist() + [0.0] * self.nb
            lam = [g[k] - F[k] for k in range(nf)]
            for k in range(nf):
                lk = lam[k]
                if (lk > 0.0 and lk > ln[k]) or (lk < 0.0 and -lk > lp[k]):
                    break
            else:
                fric[:] = lam
                return [0.0] * nf
        a = self._free_acceleration(F)
        if self._hold_kernel is not None:
            return self._hold_compiled(a)
        hold_stuck(self._inverse_inertia(), a, stuck, lp, ln, fric, dirs)
        return a

    def _hold_compiled(self, a: list[float]) -> list[float]:
        """:meth:`_constrained_acceleration`'s holding and break-away by the compiled kernel (sim/kernels.py)."""
        n, w = self.n, self._hold_work
        minv = w["minv"]
        minv[:n, :n] = pin.computeMinverse(self.model, self.data, self.q_rad)  # (the rotors' block is constant)
        acc, stuck, fric, dirs = w["a"], w["stuck"], w["fric"], w["dirs"]
        acc[:] = a
        stuck[:] = self._stuck
        w["lim_pos"][:] = self._lim_pos
        w["lim_neg"][:] = self._lim_neg
        fric[:] = self._fric
        dirs[:] = self._dir
        self._hold_kernel(minv, acc, stuck, w["lim_pos"], w["lim_neg"], fric, dirs, w["idx"], w["rows"], w["lam"])
        self._stuck[:] = stuck.tolist()
        self._fric[:] = fric.tolist()
        self._dir[:] = dirs.tolist()
        return acc.tolist()

    def _heat(self) -> None:
        """First-order joint temperature from friction power and copper loss."""
        for j, amb, _ref, cap, res, rw, _coef in self._thermal:
            p = rw * self._cur[j] ** 2
            for jj, k, _share in self._frows:
                if jj == j:
                    p += abs(self._fric[k] * self._vs[k])
            self._temp[j] += (p - (self._temp[j] - amb) / res) / cap * self.dt_s

    def _write_outputs(self) -> None:
        """Position, velocity and the Hall reading (offset, noise, quantisation) into each AxisIO."""
        base = self._noise_pos
        if base >= len(self._noise):
            # a flat list of floats (not GC-tracked), refilled in small blocks to keep each refill short
            self._noise = (self._rng.standard_normal((NOISE_BLOCK_ROWS, self.n)) * self._noise_std).ravel().tolist()
            base = 0
        self._noise_pos = base + self.n
        noise = self._noise
        meas, cur, offset, quantum, xs, vs = self._meas, self._cur, self._offset, self._quantum, self._xs, self._vs
        for j, ax in enumerate(self.axes):
            m = cur[j] + offset[j] + noise[base + j]
            qz = quantum[j]
            if qz > 0.0:
                m = round(m / qz) * qz
            meas[j] = m
            ax.position_rad = xs[j]
            ax.velocity_rad_s = vs[j]
            ax.current_measured_A = m

    def _check_stability(self) -> None:
        """Reject truths whose springs/dampers are too stiff for the step (semi-implicit Euler)."""
        dt = self.dt_s
        minv = self._inverse_inertia()
        checks: list[tuple[str, float, int]] = []
        for j in range(self.n):
            inv_i = minv[j][j]
            checks.append(("hard_stops.stiffness_Nm_per_rad", math.sqrt(self._k_stop[j] * inv_i) * dt, j))
            checks.append(("hard_stops.damping_Nm_s_per_rad", self._d_stop[j] * inv_i * dt, j))
            k = self._fdof[j]
            visc = max(self._visc_pos[j], self._visc_neg[j])
            checks.append(("friction.viscous", visc * minv[k][k] * dt, j))
        for jo, kr, _half, kg, dg in self._gear:
            inv_pair = minv[jo][jo] + minv[kr][kr]
            checks.append(("hidden.gear_stiffness_Nm_per_rad", math.sqrt(kg * inv_pair) * dt, jo))
            checks.append(("hidden.gear_damping_ratio", dg * inv_pair * dt, jo))
        for what, value, j in checks:
            if value > STABILITY_MARGIN:
                raise TruthError(f"{self.truth.source}: joints[{j}].{what}: expected a value the "
                                 f"{self.truth.physics_rate_Hz} Hz "
                                 f"step integrates stably (ω·dt or c·dt/I <= {STABILITY_MARGIN}), got {value:.2f}; "
                                 "lower it or raise physics_rate_Hz")
