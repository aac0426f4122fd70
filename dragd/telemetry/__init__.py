"""Telemetry: the cycle row's contract, the MCAP writer off the loop, the one reader.

- ``schema``  topics, schema/metadata names, `Field`, ``cycle_layout(n)`` (the daemon's row)
- ``layout``  `RowLayout`: offsets, slices, JSON Schema and the JSON encoding of a row
- ``writer``  `TelemetryWriter` (ring + writer thread + rotation), `McapFile`, ``write_file`` (offline logs)
- ``sinks``   extra row consumers: `RowSink`, `RerunSink` (``dragd run --rerun``)
- ``reader``  ``read_log``/``read_rows``/``read_events``/``read_metadata``, ``summarize``; truncated files recovered
"""
