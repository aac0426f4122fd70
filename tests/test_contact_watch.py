"""The contact detector's daemon side (dragd/control/contact_watch.py) as pure functions: the hand's force at the
grip point, the retract target, what the controller watches in each mode. The daemon with the simulator is
tests/test_contact_daemon.py's."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.config import ContactJointBands, ContactParams, load_config
from dragd.control.contact_watch import ContactWatch, grip_force
from dragd.control.controller import Controller
from dragd.control.modes import Mode
from dragd.control.params import LawParams
from dragd.model import RobotModel

pytestmark = pytest.mark.unit


def _cfg(**contact):  # noqa: ANN003, ANN202
    cfg = load_config()
    band = ContactJointBands(base_A=0.4, slow_A=0.3, speed_A_s_per_rad=0.5, accel_A_s2_per_rad=0.1,
                             slow_speed_rad_s=0.1, settling_A=0.8, held_A=0.3, held_moving_A=0.2)
    cal = ContactParams(observer_gain_per_s=25.0, margin=1.5, joints={nm: band for nm in cfg.joint_names})
    cc = cfg.contact.model_copy(update=contact)
    return cfg.model_copy(update={"contact_calibration": cal, "contact": cc})


def test_grip_force_is_the_weighted_least_squares_force_of_the_joint_torques():
    model = RobotModel.from_urdf("seed_cobot")
    model.add_grip("tool0", (0.0, 0.0, 0.05))
    rng = np.random.default_rng(3)
    for k in range(20):
        q = rng.uniform(-1.5, 1.5, 6)
        J = model.grip_jacobian(q)
        f = rng.normal(0.0, 20.0, 3)
        r = J[:3].T @ f + rng.normal(0.0, 0.5, 6)  # a hand's force plus model error
        w = np.ones(6) if k % 2 else np.where(rng.random(6) < 0.4, 0.03 ** 2, 1.0)  # resting joints weigh less
        out = np.zeros(3)
        assert grip_force(J, r, w, out)
        sw = np.sqrt(w)
        np.testing.assert_allclose(out, np.linalg.lstsq((J[:3] * sw).T, r * sw, rcond=None)[0], rtol=1e-8, atol=1e-9)
    # a resting joint whose residual is not the hand's (static friction holds it) barely moves the estimate
    q = np.array([0.3, -0.5, 0.8, 0.2, 0.6, 0.1])
    J = model.grip_jacobian(q)
    f = np.array([15.0, -10.0, 5.0])
    r = J[:3].T @ f
    r[1] = 0.0  # joint 2 stuck: the motor carries none of the hand's torque there
    w = np.ones(6)
    w[1] = 0.03 ** 2
    out, plain = np.zeros(3), np.zeros(3)
    assert grip_force(J, r, w, out) and grip_force(J, r, np.ones(6), plain)
    assert np.linalg.norm(out - f) < 0.2 * np.linalg.norm(plain - f)
    J = np.zeros((6, 6))
    J[0, 0] = 1.0  # rank 1: no force can be told
    out = np.full(3, 7.0)
    assert not grip_force(J, np.ones(6), np.ones(6), out) and (out == 7.0).all()


def test_retract_backs_off_along_the_carrying_joints_by_at_most_retract_rad():
    cfg = _cfg(retract_rad=0.03)
    w = ContactWatch.from_config(cfg, LawParams.from_config(cfg), 1e-3, compiled=False)
    det = w.det
    det.r[:] = [20.0, -6.0, 0.5, 0.0, 0.0, 0.0]
    det.d[:] = det.r / det.kt
    det.band[:] = 0.4
    q = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
    out = np.zeros(6)
    assert w.retract_step(q, q - 1.0, q + 1.0, out)
    step = out - q
    assert abs(step).max() == pytest.approx(0.03)
    assert step[0] > 0 > step[1] and step[2] == 0.0  # along the residual, only where it carries the contact
    assert step[1] / step[0] == pytest.approx(-6.0 / 20.0)
    assert w.retract_step(q, q - 0.01, q + 0.01, out) and abs(out - q).max() <= 0.01 + 1e-12  # the soft limits
    det.d[:] = 0.0
    assert not w.retract_step(q, q - 1.0, q + 1.0, out)  # nothing carries a contact: nothing to back off along


def test_the_controller_watches_hold_track_identify_and_drag_and_says_why_not():
    cfg = _cfg()
    model = RobotModel.from_config(cfg)
    c = Controller.from_config(cfg, model.position_limits_rad)
    assert c.contact is not None and c.contact.calibrated
    c.mode = Mode.HOLD
    assert c.contact_want() == "hold"
    c.stop_after_hold_at = 1.0
    assert c.contact_want() == "" and "stopping" in c.contact.why_not
    c.stop_after_hold_at = None
    c.mode = Mode.DRAG
    assert c.contact_want() == "drag"
    off = cfg.model_copy(update={"contact": cfg.contact.model_copy(update={"enabled": False})})
    c2 = Controller.from_config(off, model.position_limits_rad)
    c2.mode = Mode.DRAG
    assert c2.contact_want() == "" and "disabled" in c2.contact.why_not
    raw = load_config()  # no bands: only the drag residual
    c3 = Controller.from_config(raw, model.position_limits_rad)
    c3.mode = Mode.HOLD
    assert c3.contact_want() == "" and "not calibrated" in c3.contact.why_not
    c3.mode = Mode.DRAG
    assert c3.contact_want() == "drag"


def test_status_shows_the_bands_and_each_modes_sensitivity_and_reaction():
    from dragd.config import ContactModeConfig

    cfg = _cfg(hold=ContactModeConfig(sensitivity=2.0, reaction="retract"),
               track=ContactModeConfig(sensitivity=0.5, reaction="compliant"))
    w = ContactWatch.from_config(cfg, LawParams.from_config(cfg), 1e-3, compiled=False)
    st = w.status(cfg.joint_names)
    assert st["modes"]["hold"] == {"sensitivity": 2.0, "reaction": "retract"}
    assert st["modes"]["track"] == {"sensitivity": 0.5, "reaction": "compliant"}
    assert st["modes"]["identify"] == {"sensitivity": 1.0, "reaction": "stop"}
    assert st["thresholds_A"]["hold"] == [0.2] * 6 and st["thresholds_A"]["track"] == [0.8] * 6
    assert st["bands_A"]["joint3"]["held_A"] == 0.3
    w.select("hold")
    assert w.det.band.shape == (6,)
