"""Golden traces of the daemon's cycle (see trace.py)."""
