"""Teach and replay: record what the hand shows (drag), replay it smoothly in CSP (docs/TEACH.md).

* ``program``   the versioned program file (YAML) and its schema
* ``recorder``  the daemon-side recorder (positions at a chosen rate, marked waypoints)
* ``keyframes`` post-processing of a continuous recording
* ``profile``   jerk-limited double-S profile
* ``kinematics`` FK / damped-least-squares IK (Pinocchio), the circle through three points
* ``plan``      replay planning: PTP, circle, spline, path; limits, re-timing, feed-forward
* ``worker``    the planner process the daemon delegates to
"""
