"""Running the simulated rig: benchmarks, the demo, experiments (not part of the runtime)."""
