"""The ROS 2 bridge (``dragd ros2``, docs/ROS2.md): a process beside the daemon, a client of its control socket.

It never runs inside the daemon: the 1 kHz process knows nothing of ROS, and every limit, guard and monitor stays
the daemon's. Needs the ``ros2`` extra (``pip install 'dragd[ros2]'``: rclpy and the message packages from PyPI's
ROS 2 wheels, no ROS installation).
"""

from __future__ import annotations

INSTALL_HINT = "pip install 'dragd[ros2]' (rclpy and the message packages as wheels: no ROS installation needed)"

MODULES = ("rclpy", "sensor_msgs.msg", "std_msgs.msg", "std_srvs.srv", "trajectory_msgs.msg", "diagnostic_msgs.msg",
           "builtin_interfaces.msg", "rosgraph_msgs.msg")


def unavailable() -> str | None:
    """Why the bridge cannot run here (a module of the ``ros2`` extra missing or broken), else None."""
    import importlib

    for name in MODULES:
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - an import error of a native extension can be anything
            return f"the ROS 2 bridge needs {name} ({type(exc).__name__}: {exc}); {INSTALL_HINT}"
    return None
