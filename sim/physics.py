"""Arm physics of the simulated robot: rigid-body dynamics (Pinocchio ABA) plus the drive train's truth.

Per fixed step (``truth.physics_rate_Hz``, >= 4 kHz), reading each joint's :class:`~sim.axis.AxisIO`:

* current loop: first-order lag of the motor current towards ``current_demand_A`` (zero with the power stage off);
  joint torque = true K_t · I; the Hall reading adds noise and quantisation (``current_measured_A``);
* friction: direction-asymmetric Stribeck curve plus viscous slope, with stick–slip as a constraint: a joint at
  rest gets exactly the torque that keeps it at rest (solved for all stuck joints together through M⁻¹) until
  that torque exceeds its static level, and a sliding joint whose velocity crosses zero sticks — no chatter,
  no drift;
* brakes: an engaged brake adds its holding torque to the joint's static and sliding friction (locks it, slips
  above the holding torque);
* hard stops: spring–damper beyond each limit, never pulling;
* hidden effects (off by default): torque ripple, load-dependent friction, thermal friction drift, Hall offset,
  backlash (a separate rotor inertia coupled to the output through a dead zone);
* semi-implicit Euler: v += a·dt, then q += v·dt.

Rotor inertia × gear² enters the Pinocchio model as armature (joints without backlash), so ABA includes it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pinocchio as pin

from sim.axis import AxisIO
from sim.truth import Truth, TruthError

if TYPE_CHECKING:
    from dragd.model import RobotModel

NOISE_BLOCK_ROWS = 4096
STABILITY_MARGIN = 0.5  # max ω·dt (springs) and c·dt/I (dampers) accepted at the truth's step


class ExternalTorque(Protocol):
    """Something that writes the operator's joint torques each step (see :class:`sim.operator.Operator`)."""

    def apply(self, t_s: float, q_rad: np.ndarray, dq_rad_s: np.ndarray, out_Nm: np.ndarray) -> None: ...


class ArmPhysics:
    """The simulated arm: call :meth:`step` once per physics step after the drives' ``update``."""

    def __init__(self, truth: Truth, model: RobotModel | pin.Model, axes: list[AxisIO]) -> None:
        src = getattr(model, "model", model)
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

        # private model copy: the truth's gravity and armature (never touch the caller's constant model)
        self.model = pin.Model(src)
        self.model.gravity.linear = np.asarray(truth.gravity_m_s2, dtype=float)
        backlash = np.array([j.hidden.backlash_rad > 0 for j in joints])
        self._bj = np.flatnonzero(backlash)  # joints with a separate rotor
        self.nb = nb = len(self._bj)
        self.nf = nf = n + nb
        armature = np.array([j.armature_kgm2 for j in joints])
        self.model.armature[:] = np.where(backlash, 0.0, armature)
        self.data = self.model.createData()

        # state: positions/velocities of the n links followed by the nb rotors (rotor angle in joint units)
        self._x = np.zeros(nf)
        self._v = np.zeros(nf)
        self.q_rad = self._x[:n]
        self.dq_rad_s = self._v[:n]
        self.rotor_rad = self._x[n:]
        self._fdof = np.arange(n)
        self._fdof[self._bj] = n + np.arange(nb)
        self._fsl: slice | np.ndarray = slice(0, n) if nb == 0 else self._fdof  # friction DOF of each joint
        self._rotor_inertia = armature[self._bj]

        # drive train
        self._kt = np.array([j.torque_constant_Nm_per_A for j in joints])
        self._alpha = np.array([1.0 - math.exp(-self.dt_s / j.current_loop_time_constant_s) for j in joints])
        self._offset = np.array([j.hidden.current_offset_A for j in joints])
        self._noise_std = np.array([j.current_noise_std_A for j in joints])
        quantum = np.array([j.current_quantum_A for j in joints])
        self._quantum = np.where(quantum > 0, quantum, 1.0)
        self._quantised = quantum > 0
        self._rng = np.random.default_rng(truth.noise_seed)
        self._noise = np.zeros((NOISE_BLOCK_ROWS, n))
        self._noise_row = NOISE_BLOCK_ROWS

        # friction truth in DOF space (zero on the outputs of backlash joints: their friction is on the rotor)
        def dof(values: list[float]) -> np.ndarray:
            out = np.zeros(nf)
            out[self._fsl] = values
            return out

        fr = [j.friction for j in joints]
        self._fc_pos = dof([f.coulomb_pos_Nm for f in fr])
        self._fc_neg = dof([-f.coulomb_neg_Nm for f in fr])  # magnitudes
        self._fs_pos = dof([f.static_pos for f in fr])
        self._fs_neg = dof([-f.static_neg for f in fr])
        self._vs_inv = dof([1.0 / f.stribeck_velocity_rad_s for f in fr])
        self._delta = dof([f.stribeck_exponent for f in fr])
        self._visc_pos = dof([f.viscous_pos_Nm_s_per_rad for f in fr])
        self._visc_neg = dof([f.viscous_neg_Nm_s_per_rad for f in fr])
        self._hold = dof([j.brake_holding_torque_Nm for j in joints])
        self._load_coef = np.array([j.hidden.load_friction_per_Nm for j in joints])
        self._load_on = bool(self._load_coef.any())

        # hard stops (outputs)
        self._lower = np.array([j.hard_stops.lower_rad for j in joints])
        self._upper = np.array([j.hard_stops.upper_rad for j in joints])
        self._k_stop = np.array([j.hard_stops.stiffness_Nm_per_rad for j in joints])
        self._d_stop = np.array([j.hard_stops.damping_Nm_s_per_rad for j in joints])

        # ripple: one row per (joint, harmonic); the angle is the friction DOF's (rotor for backlash joints)
        rows = [(i, r) for i, j in enumerate(joints) for r in j.hidden.ripple if r.amplitude_Nm > 0]
        self._ripple_joint = np.array([i for i, _ in rows], dtype=int)
        self._ripple_dof = self._fdof[self._ripple_joint] if rows else self._ripple_joint
        self._ripple_amp = np.array([r.amplitude_Nm for _, r in rows])
        self._ripple_k = np.array([r.cycles_per_rev * (joints[i].gear_ratio if r.reference == "motor" else 1.0)
                                   for i, r in rows])
        self._ripple_phase = np.array([r.phase_rad for _, r in rows])

        # backlash coupling
        self._half_gap = np.array([joints[i].hidden.backlash_rad / 2 for i in self._bj])
        self._k_gear = np.array([joints[i].hidden.gear_stiffness_Nm_per_rad for i in self._bj])
        self._d_gear = np.array([joints[i].hidden.gear_damping_Nm_s_per_rad for i in self._bj])

        # thermal
        th = [j.hidden.thermal for j in joints]
        self._thermal_on = any(t is not None for t in th)
        self._th_ambient = np.array([t.ambient_C if t else 25.0 for t in th])
        self._th_ref = np.array([t.reference_C if t else 25.0 for t in th])
        self._th_cap = np.array([t.heat_capacity_J_per_K if t else 1.0 for t in th])
        self._th_res = np.array([t.thermal_resistance_K_per_W if t else 1.0 for t in th])
        self._th_rw = np.array([t.winding_resistance_ohm if t else 0.0 for t in th])
        self._th_coef = np.array([t.friction_coefficient_per_K if t else 0.0 for t in th])
        self._th_mask = np.array([t is not None for t in th])
        self.temperature_C = np.array([(t.initial_C if t.initial_C is not None else t.ambient_C) if t else 25.0
                                       for t in th])
        self._scale = np.ones(n)

        # drive signals and outputs (joint space)
        self.current_demand_A = np.zeros(n)
        self.power_on = np.zeros(n, dtype=bool)
        self.brakes = np.ones(n, dtype=bool)
        self.current_A = np.zeros(n)  # actual motor current
        self.current_measured_A = np.zeros(n)
        self.tau_motor_Nm = np.zeros(n)
        self.tau_ext_Nm = np.zeros(n)  # operator's joint torques (written by the operator, or directly)
        self.tau_stop_Nm = np.zeros(n)
        self.tau_friction_Nm = np.zeros(n)  # torque friction and brakes exert on each joint (stiction included)
        self.gravity_Nm = np.zeros(n)  # G(q) at the last step that needed it (load-dependent friction)
        self.operator: ExternalTorque | None = None

        # stick–slip bookkeeping (DOF space)
        self.stuck = np.zeros(nf, dtype=bool)
        self._dir = np.zeros(nf)  # sliding direction (+1/−1), 0 while stuck
        self._sticky = np.zeros(nf, dtype=bool)  # DOFs with friction or brake > 0 (can stick)
        self._F = np.zeros(nf)
        self._fric = np.zeros(nf)
        self._lim_pos = np.zeros(nf)
        self._lim_neg = np.zeros(nf)
        self._minv = np.zeros((nf, nf))
        self._a = np.zeros(nf)
        self._v_old = np.zeros(nf)
        self._meas = np.zeros(n)

        self.t_s = 0.0
        self.steps = 0
        self.set_state(np.array([j.initial_position_rad for j in joints]))
        self._check_stability()
        self._write_outputs()

    # ------------------------------------------------------------------------------------------- state

    def set_state(self, q_rad: np.ndarray, dq_rad_s: np.ndarray | None = None) -> None:
        """Teleport the arm (rotors follow with the gap centred); a zero velocity leaves every joint stuck."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        if q.shape[0] != self.n:
            raise ValueError(f"set_state: expected {self.n} joint positions, got {q.shape[0]}")
        dq = np.zeros(self.n) if dq_rad_s is None else np.asarray(dq_rad_s, dtype=float).reshape(-1)
        self._x[: self.n] = q
        self._v[: self.n] = dq
        self._x[self.n:] = q[self._bj]
        self._v[self.n:] = dq[self._bj]
        self._dir[:] = np.sign(self._v)
        self.stuck[:] = False
        self.stuck[self._fsl] = self._v[self._fsl] == 0.0
        self._dir[self.stuck] = 0.0
        self.current_A[:] = 0.0
        self._write_outputs()

    def snapshot(self) -> dict[str, Any]:
        """The truth state as plain lists (JSON-ready)."""
        return {
            "t": self.t_s,
            "steps": self.steps,
            "q_rad": self.q_rad.tolist(),
            "dq_rad_s": self.dq_rad_s.tolist(),
            "current_A": self.current_A.tolist(),
            "current_measured_A": self.current_measured_A.tolist(),
            "current_demand_A": self.current_demand_A.tolist(),
            "tau_motor_Nm": self.tau_motor_Nm.tolist(),
            "tau_ext_Nm": self.tau_ext_Nm.tolist(),
            "tau_friction_Nm": self.tau_friction_Nm.tolist(),
            "tau_stop_Nm": self.tau_stop_Nm.tolist(),
            "stuck": self.stuck[self._fsl].tolist(),
            "brakes": self.brakes.tolist(),
            "power_on": self.power_on.tolist(),
            "temperature_C": self.temperature_C.tolist(),
            "rotor_rad": self.rotor_rad.tolist(),
        }

    def static_friction_Nm(self, joint: int, direction: int) -> float:
        """The breakaway level of one joint (friction + engaged brake) in a direction (+1/−1), at present."""
        self._limits()
        k = self._fdof[joint]
        return float(self._lim_pos[k] if direction > 0 else self._lim_neg[k])

    # ------------------------------------------------------------------------------------------- step

    def step(self) -> None:
        """Advance one physics step."""
        n, dt = self.n, self.dt_s
        axes = self.axes
        self.current_demand_A[:] = [ax.current_demand_A for ax in axes]
        self.power_on[:] = [ax.power_stage_on for ax in axes]
        self.brakes[:] = [ax.brake_engaged for ax in axes]

        # current loop: the Hall offset makes the loop deliver demand − offset
        cur = self.current_A
        cur += self._alpha * (self.current_demand_A - self._offset - cur)
        cur *= self.power_on
        np.multiply(self._kt, cur, out=self.tau_motor_Nm)

        q, dq = self.q_rad, self.dq_rad_s
        if self.operator is not None:
            self.operator.apply(self.t_s, q, dq, self.tau_ext_Nm)

        F = self._F
        F[:n] = self.tau_ext_Nm
        F[n:] = 0.0
        self._hard_stops(q, dq)
        F[:n] += self.tau_stop_Nm
        F[self._fsl] += self.tau_motor_Nm
        if self._ripple_amp.size:
            rip = self._ripple_amp * np.sin(self._ripple_k * self._x[self._ripple_dof] + self._ripple_phase)
            F += np.bincount(self._ripple_dof, rip, minlength=self.nf)
        if self.nb:
            self._gear_coupling(F)
        if self._load_on:
            self.gravity_Nm[:] = pin.computeGeneralizedGravity(self.model, self.data, q)
        if self._thermal_on:
            self._scale[:] = np.where(self._th_mask, 1.0 + self._th_coef * (self.temperature_C - self._th_ref), 1.0)

        self._limits()
        stuck = self.stuck
        fric = self._fric
        any_stuck = bool(stuck.any())
        if any_stuck and stuck.all():
            fric[:] = 0.0
        else:
            self._sliding_friction()  # into fric (0 on stuck DOFs)
        F += fric
        a = self._a
        if not any_stuck:
            self._free_acceleration(F, a)
        else:
            self._constrained_acceleration(F, a)

        # semi-implicit Euler; a sliding joint whose velocity reverses sticks (friction would have stopped it)
        v = self._v
        self._v_old[:] = v
        v += a * dt
        if not stuck.all():
            halt = (v * self._dir <= 0.0) & self._sticky & ~stuck
            if halt.any():
                v[halt] = 0.0
                stuck |= halt
                self._dir[halt] = 0.0
            moving = ~stuck & (v != 0.0)
            self._dir[moving] = np.sign(v[moving])
        self._x += v * dt

        self.tau_friction_Nm[:] = fric[self._fsl]  # stiction included (solved into fric)
        if self._thermal_on:
            self._heat()
        self.t_s = (self.steps + 1) * dt
        self.steps += 1
        self._write_outputs()

    # ------------------------------------------------------------------------------------------- parts

    def _limits(self) -> None:
        """Breakaway levels per direction (friction × thermal scale + load term + engaged brake), DOF space."""
        lp, ln = self._lim_pos, self._lim_neg
        if not (self._thermal_on or self._load_on):
            np.copyto(lp, self._fs_pos)
            np.copyto(ln, self._fs_neg)
        else:
            extra = self._load_coef * np.abs(self.gravity_Nm)
            lp[self._fsl] = self._fs_pos[self._fsl] * self._scale + extra
            ln[self._fsl] = self._fs_neg[self._fsl] * self._scale + extra
        hold = np.zeros(self.nf)
        hold[self._fsl] = self.brakes
        hold *= self._hold
        lp += hold
        ln += hold
        np.greater(lp + ln, 0.0, out=self._sticky)

    def _sliding_friction(self) -> None:
        """Kinetic friction (Stribeck + viscous + slipping brake) of sliding DOFs into ``self._fric``."""
        v = self._v
        d = self._dir
        pos = d > 0
        fc = np.where(pos, self._fc_pos, self._fc_neg)
        visc = np.where(pos, self._visc_pos, self._visc_neg)
        if self._thermal_on or self._load_on:
            scale = np.ones(self.nf)
            scale[self._fsl] = self._scale
            extra = np.zeros(self.nf)
            extra[self._fsl] = self._load_coef * np.abs(self.gravity_Nm)
            fc = fc * scale + extra
            visc = visc * scale
        lim = np.where(pos, self._lim_pos, self._lim_neg)  # static (+ load, scale) + brake
        hold = np.zeros(self.nf)
        hold[self._fsl] = self.brakes
        hold *= self._hold
        fc += hold  # a slipping brake holds its torque
        stribeck = np.exp(-np.power(np.abs(v) * self._vs_inv, self._delta))
        mag = fc + (lim - fc) * stribeck
        np.multiply(d, mag, out=self._fric)
        self._fric += visc * v
        np.negative(self._fric, out=self._fric)
        self._fric[self.stuck] = 0.0

    def _hard_stops(self, q: np.ndarray, dq: np.ndarray) -> None:
        ts = self.tau_stop_Nm
        below = q < self._lower
        above = q > self._upper
        if not (below.any() or above.any()):
            ts[:] = 0.0
            return
        pen = np.where(below, q - self._lower, 0.0) + np.where(above, q - self._upper, 0.0)
        tau = -self._k_stop * pen - self._d_stop * dq * (below | above)
        # a stop pushes out, never pulls in
        tau = np.where(below, np.maximum(tau, 0.0), tau)
        tau = np.where(above, np.minimum(tau, 0.0), tau)
        ts[:] = tau

    def _gear_coupling(self, F: np.ndarray) -> None:
        n, bj = self.n, self._bj
        gap = self._x[n:] - self._x[bj]
        e = gap - np.clip(gap, -self._half_gap, self._half_gap)
        contact = e != 0.0
        tau = self._k_gear * e + self._d_gear * (self._v[n:] - self._v[bj]) * contact
        # the damper only acts in contact and never pulls the teeth together
        tau = np.where(e > 0, np.maximum(tau, 0.0), np.where(e < 0, np.minimum(tau, 0.0), 0.0))
        F[bj] += tau
        F[n:] -= tau

    def _free_acceleration(self, F: np.ndarray, out: np.ndarray) -> None:
        """Unconstrained accelerations: ABA for the links (armature included), J⁻¹·τ for separate rotors."""
        n = self.n
        out[:n] = pin.aba(self.model, self.data, self.q_rad, self.dq_rad_s, F[:n])
        if self.nb:
            out[n:] = F[n:] / self._rotor_inertia

    def _inverse_inertia(self) -> np.ndarray:
        minv = self._minv
        minv[: self.n, : self.n] = pin.computeMinverse(self.model, self.data, self.q_rad)
        if self.nb:
            minv[self.n:, self.n:] = np.diag(1.0 / self._rotor_inertia)
        return minv

    def _constrained_acceleration(self, F: np.ndarray, out: np.ndarray) -> None:
        """Accelerations with stuck DOFs held by stiction (their friction torque solved exactly).

        A stuck DOF whose required holding torque exceeds its static level in the direction it would move breaks
        away: it leaves the stuck set and gets its static level as sliding friction (the Stribeck curve at v = 0).
        The worst excess is released first and the rest re-solved, since releasing one changes the others' need.
        """
        stuck, fric = self.stuck, self._fric
        if self.nb == 0 and stuck.all():
            # at rest everywhere: the holding torque is G(q) − F, no inertia needed unless something breaks away
            lam = np.asarray(pin.computeGeneralizedGravity(self.model, self.data, self.q_rad)) - F
            excess = np.where(lam > 0, lam - self._lim_neg, -lam - self._lim_pos)
            if excess.max() <= 0.0:
                fric[:] = lam
                out[:] = 0.0
                return
        self._free_acceleration(F, out)
        minv = self._inverse_inertia()
        S = np.flatnonzero(stuck)
        lam = np.zeros(0)
        while S.size:
            lam = -np.linalg.solve(minv[np.ix_(S, S)], out[S])
            excess = np.where(lam > 0, lam - self._lim_neg[S], -lam - self._lim_pos[S])
            i = int(np.argmax(excess))
            if excess[i] <= 0.0:
                break
            k = int(S[i])
            d = -1.0 if lam[i] > 0 else 1.0  # it moves against the torque that would have held it
            f = -d * (self._lim_pos[k] if d > 0 else self._lim_neg[k])
            out += minv[:, k] * f
            fric[k] = f
            stuck[k] = False
            self._dir[k] = d
            S = np.delete(S, i)
            lam = np.zeros(0)
        if S.size:
            out += minv[:, S] @ lam
            out[S] = 0.0
            fric[S] = lam

    def _heat(self) -> None:
        """First-order joint temperature from friction power and copper loss."""
        p_fric = np.abs(self._fric * self._v)[self._fsl]
        p = p_fric + self._th_rw * self.current_A**2
        dT = (p - (self.temperature_C - self._th_ambient) / self._th_res) / self._th_cap * self.dt_s
        self.temperature_C += np.where(self._th_mask, dT, 0.0)

    def _write_outputs(self) -> None:
        """Position, velocity and the Hall reading (noise, quantisation, offset) into each AxisIO."""
        if self._noise_row >= NOISE_BLOCK_ROWS:
            self._noise[:] = self._rng.standard_normal((NOISE_BLOCK_ROWS, self.n)) * self._noise_std
            self._noise_row = 0
        meas = self._meas
        np.add(self.current_A, self._offset, out=meas)
        meas += self._noise[self._noise_row]
        self._noise_row += 1
        rounded = np.round(meas / self._quantum) * self._quantum
        np.copyto(meas, rounded, where=self._quantised)
        self.current_measured_A[:] = meas
        for ax, p, w, c in zip(self.axes, self.q_rad.tolist(), self.dq_rad_s.tolist(), meas.tolist()):
            ax.position_rad = p
            ax.velocity_rad_s = w
            ax.current_measured_A = c

    def _check_stability(self) -> None:
        """Reject truths whose springs/dampers are too stiff for the step (semi-implicit Euler)."""
        dt = self.dt_s
        minv = self._inverse_inertia()
        inv_i = np.diag(minv)[: self.n]
        checks = [("hard_stops.stiffness", math.sqrt(k * m) * dt, j) for j, (k, m) in enumerate(zip(self._k_stop, inv_i))]
        checks += [("hard_stops.damping", c * m * dt, j) for j, (c, m) in enumerate(zip(self._d_stop, inv_i))]
        for j in range(self.n):
            k = self._fdof[j]
            inv_f = minv[k, k]
            checks.append(("friction.viscous", max(self._visc_pos[k], self._visc_neg[k]) * inv_f * dt, j))
        for r, j in enumerate(self._bj):
            inv_pair = inv_i[j] + 1.0 / self._rotor_inertia[r]
            checks.append(("hidden.gear_stiffness", math.sqrt(self._k_gear[r] * inv_pair) * dt, int(j)))
            checks.append(("hidden.gear_damping", self._d_gear[r] * inv_pair * dt, int(j)))
        for what, value, j in checks:
            if value > STABILITY_MARGIN:
                raise TruthError(f"{self.truth.source}: joints[{j}].{what}: expected a value the {self.truth.physics_rate_Hz} Hz "
                                 f"step integrates stably (ω·dt or c·dt/I <= {STABILITY_MARGIN}), got {value:.2f}; "
                                 "lower it or raise physics_rate_Hz")
