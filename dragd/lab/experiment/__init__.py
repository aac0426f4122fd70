"""Experiments on the (simulated) robot: seed 001's start-up tests, the sine sweep, drag quality.

They drive the simulated robot and the daemon as separate processes, measure with the daemon's encoders and
the operator's force gauge (the sim's scripted hand: the seed's weight-and-pulley with a force sensor), and use
only the configuration and identified parameters for compensation — never the simulator's truth.
"""
