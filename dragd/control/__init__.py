"""The control law of every mode and its estimate: pure functions and state over numpy arrays (no asyncio, no CAN,
no pydantic)."""
