"""The replay service: a recording re-run through the fusion core offline, and its report.

============== =================================================================
run            ``replay``: settings -> feed the fusion core -> outputs -> report
decided        ``DecisionReplayer``: the live fusion's decision record, call by call
report_stream  the report as a stream (``Recorded``: fixes matched as they are read)
evaluate       fixes against the recorded truth (math in ``diffpos.metrics``)
synthetic      synthetic runs without Zenoh (tests, benchmarks, the dashboard's demo)
============== =================================================================

It reads recordings with :mod:`diffpos_services.recording` (the MCAP file format) and re-runs
:class:`diffpos_services.fusion.core.FusionCore` (the one service it may import).
"""
