"""Position streams into TRACK over the control socket: followed (the simulator's truth), ended by the client, by
its silence (a dead client) or by a refused sample; never opened from drag; another client's flood of stream
requests answered on the control socket's thread, none on the cycle's loop, the stream followed as without it. The
ROS 2 bridge's command topic rides on exactly this (tests/test_ros2_bridge.py).

On the lockstep clock: the client stamps its samples with the arm's time (``rig.now()``) and sends one every 10 ms
of it, so the lag behind the path and the silence's timeout are the daemon's own figures, not the host's."""

from __future__ import annotations

import json
import math
import socket
import threading
from typing import Any

import numpy as np
import pytest

from dragd.lab.rig import Rig

from daemon_helpers import cycle_rows

pytestmark = pytest.mark.lockstep

STEP = np.array([0.25, -0.15, 0.2, 0.3, -0.25, 0.3])  # rad: each joint's move (well inside the limits)


def path(q0: np.ndarray, t: float, T: float) -> np.ndarray:
    """A smooth move (cosine blend) from q0 by STEP over T seconds."""
    x = min(max(t / T, 0.0), 1.0)
    return q0 + STEP * (1.0 - math.cos(math.pi * x)) / 2.0


class Flood:
    """A client flooding the daemon with ``stream`` requests for stream ``sid`` on a connection of its own, 50 at a
    time, from a thread, until ``stop``."""

    def __init__(self, path: str, sid: int) -> None:
        self.path, self.sid = path, sid
        self.sent = self.refused = 0
        self.other: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        line = json.dumps({"cmd": "stream", "stream": self.sid, "t_s": 0.0, "q_rad": [0.0] * 6}).encode() + b"\n"
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(30.0)
            s.connect(self.path)
            f = s.makefile("rb")
            while not self._stop.is_set():
                s.sendall(line * 50)
                for _ in range(50):
                    r = json.loads(f.readline())
                    self.sent += 1
                    if not r["ok"] and f"no stream {self.sid}" in r["error"]:
                        self.refused += 1
                    else:
                        self.other.append(str(r))

    def stop(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join(30.0)
        return {"sent": self.sent, "refused": self.refused, "other": self.other[:3]}


def held(rig: Rig) -> np.ndarray:
    rig.must("start")
    rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold")
    rig.sleep(0.3)
    return np.array(rig.must("status")["q_rad"])


def test_stream_follows_the_path_then_ends_into_hold(tmp_path):
    with Rig("stream", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        q0 = held(rig)
        opened = rig.must("stream_open", label="test")
        assert opened["mode"] == "track" and opened["delay_s"] == 0.05
        sid = opened["stream"]
        assert rig.must("status")["drive_mode"] == "csp"
        c0 = rig.must("status")["control"]
        flood = Flood(rig.socket, sid + 1000)  # another client's stream requests all along (refused: no such stream)
        lags = []
        sent_t, sent_q = [], []
        t0 = rig.now()
        while (t := rig.now()) - t0 < 2.4:
            q = path(q0, t - t0, 2.0)
            rig.must("stream", stream=sid, t_s=t, q_rad=q.tolist())
            sent_t.append(t)
            sent_q.append(q)
            if 0.8 < t - t0 < 1.2:  # mid-path: the arm (sim truth) against what was sent
                truth = np.array(rig.sim_call("state")["q_rad"])
                t_truth = t - t0
                # how far behind the sent path the arm is, in time: the best matching time along the path
                grid = np.linspace(t_truth - 0.3, t_truth, 301)
                err = [np.abs(path(q0, g, 2.0) - truth).max() for g in grid]
                lags.append(t_truth - grid[int(np.argmin(err))])
            rig.sleep(0.01)
        flooded = flood.stop()
        st = rig.must("state")["stream"]
        assert st["state"] == "running" and st["samples"] == len(sent_t), st
        rig.must("stream_close", stream=sid)
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the stream's close")
        rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 2.0, "the drives back in CST")
        rig.sleep(0.3)
        end = rig.must("status")
        truth = np.array(rig.sim_call("state")["q_rad"])
        refused = rig.call("stream", stream=sid, t_s=rig.now(), q_rad=q0.tolist())
        ev = rig.must("events", since=0)["events"]
        c1 = rig.must("status")["control"]
    # the flood and the samples were answered on the control socket's thread, none on the cycle's loop (which ran
    # the path as without it: every sample in, the buffer never dry, the lag below)
    assert flooded["sent"] > len(sent_t) and flooded["refused"] == flooded["sent"], flooded
    # (+ the close and the refused sample after it)
    assert c1["off_cycle"] - c0["off_cycle"] == flooded["sent"] + len(sent_t) + 2, (c0, c1, flooded)
    assert end["faults"] == [], end["faults"]
    assert end["stream"]["end"] == "closed" and end["stream"]["outcome"] == "stream closed", end["stream"]
    assert end["stream"]["dry_cycles"] == 0, end["stream"]  # a 100 Hz stream never ran the 50 ms buffer dry
    err = np.degrees(np.abs(truth - sent_q[-1]))
    assert err.max() < 0.5, err  # held where the stream ended (the drives' loops, gravity + friction fed forward)
    # the arm follows the path about the playback delay (50 ms) + the drives' lag behind what was sent
    assert lags and 0.05 <= float(np.median(lags)) <= 0.07, lags  # (measured 0.061 s: 11 ms of the drives' lag)
    assert not refused["ok"] and "ended (stream closed)" in refused["error"], refused
    names = [e["name"] for e in ev]
    assert "stream_open" in names and any(e["name"] == "track_end" and e["outcome"] == "stream closed" for e in ev)


def test_a_silent_client_ends_the_stream_into_hold(tmp_path):
    mcap = tmp_path / "silent.mcap"
    with Rig("stream-dead", workdir=tmp_path, telemetry=mcap) as rig:
        rig.start_sim()
        rig.start_daemon()
        q0 = held(rig)
        sid = rig.must("stream_open")["stream"]
        # half the path, then nothing (the client died mid-motion, at its fastest)
        t0 = rig.now()
        last = q0
        while (t := rig.now()) - t0 < 0.6:
            t_last = t
            last = path(q0, t - t0, 1.2)
            rig.must("stream", stream=sid, t_s=t, q_rad=last.tolist())
            rig.sleep(0.01)
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the client fell silent")
        gone_s = rig.now() - t_last
        rig.sleep(0.5)
        end = rig.must("status")
        truth = np.array(rig.sim_call("state")["q_rad"])
        rig.sleep(0.3)
        later = np.array(rig.sim_call("state")["q_rad"])
    assert end["stream"]["end"] == "timeout" and "no sample for 0.5 s" in end["stream"]["outcome"], end["stream"]
    assert end["faults"] == [], end["faults"]
    assert 0.5 <= gone_s <= 0.51, gone_s  # timeout 0.5 s (the cycle's time) after the last sample, seen by a 10 ms poll
    rows = cycle_rows(mcap)
    hold = np.flatnonzero(rows["mode"] == "hold")
    hold = hold[hold > np.flatnonzero(rows["mode"] == "track")[-1]]
    # the reference stopped on the last sample sent and holds there: nothing is extrapolated
    assert np.abs(rows["q_ref_rad"][hold] - last).max() < 1e-9
    # the arm stopped near it (braking from 0.33 rad/s within the 50 ms buffer: the drives' loops overshoot a
    # little) and stays where it stopped
    assert np.degrees(np.abs(truth - last)).max() < 2.0, np.degrees(truth - last)
    assert np.degrees(np.abs(later - truth)).max() < 0.05


def test_a_refused_sample_ends_the_stream_with_its_reason(tmp_path):
    with Rig("stream-refuse", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        q0 = held(rig)
        far = rig.call("stream", stream=1, t_s=0.0, q_rad=q0.tolist())
        assert not far["ok"] and "no stream 1" in far["error"], far
        sid = rig.must("stream_open")["stream"]
        bad_first = rig.call("stream", stream=sid, t_s=1.0, q_rad=(q0 + 0.1).tolist())
        assert not bad_first["ok"] and "first sample" in bad_first["error"] and "a stream starts where the arm is" \
            in bad_first["error"], bad_first
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the refusal")
        rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 2.0, "CST")
        sid = rig.must("stream_open")["stream"]
        t = 100.0
        rig.must("stream", stream=sid, t_s=t, q_rad=q0.tolist())
        lim = rig.must("robot")["position_limits_rad"]
        beyond = q0.copy()
        beyond[2] = lim[2][1] + 0.01
        over = rig.call("stream", stream=sid, t_s=t + 0.01, q_rad=beyond.tolist())
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the refusal")
        st = rig.must("status")
        dq = rig.call("stream", stream=sid, t_s=t + 0.02, q_rad=q0.tolist())
        rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 2.0, "CST")
        # a step in the target (too fast between samples) is refused before anything moves
        sid = rig.must("stream_open")["stream"]
        rig.must("stream", stream=sid, t_s=t, q_rad=q0.tolist())
        step = q0.copy()
        step[0] += 0.1
        fast = rig.call("stream", stream=sid, t_s=t + 0.001, q_rad=step.tolist())
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the refusal")
        rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 2.0, "CST")
        # a sample stamped beyond stream.max_lead_s (1 s) after the playback: the field, the latest it may be
        sid = rig.must("stream_open")["stream"]
        rig.must("stream", stream=sid, t_s=t, q_rad=q0.tolist())
        ahead = rig.call("stream", stream=sid, t_s=t + 1.5, q_rad=q0.tolist())
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "hold after the refusal")
        rig.must("mode", mode="drag")
        from_drag = rig.call("stream_open")
        truth = np.array(rig.sim_call("state")["q_rad"])
    assert not over["ok"] and "joint3" in over["error"] and "position limits" in over["error"], over
    assert st["stream"]["end"] == "refused" and "position limits" in st["stream"]["outcome"], st["stream"]
    assert not dq["ok"] and "ended" in dq["error"], dq
    assert not fast["ok"] and "rad/s" in fast["error"] and "encoder_plausible_speed" in fast["error"], fast
    assert not ahead["ok"] and ahead["error"].startswith(f"stream {sid}: t_s {t + 1.5:.6f}: expected at most "), ahead
    latest = float(ahead["error"].split("expected at most ")[1].split()[0])
    # the first sample went in delay_s (0.05 s) ahead of the playback, which had not moved yet: t + 0.95 at most
    assert abs(latest - (t + 1.0 - 0.05)) < 0.002 and "stream.max_lead_s 1 s after the playback" in ahead["error"], \
        ahead
    assert not from_drag["ok"] and "never takes the arm from the operator's hand" in from_drag["error"], from_drag
    assert np.degrees(np.abs(truth - q0)).max() < 0.5  # nothing refused ever moved the arm
