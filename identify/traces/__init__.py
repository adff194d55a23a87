"""Recorded traces: reading and writing the trace format, event extraction, the reduced
(per-cycle) analysis, and ``analyze``, which composes them."""
