"""Telemetry: the cycle row's schema, the MCAP writer off the loop, the one reader."""
