"""The MCAP file format: write, read, repair, summarise (pure Python, no Zenoh).

Split by role like the ``mcap`` package:

========== =====================================================================
errors     ``RecordingError`` (a ``DiffposError``, exit code 2), ``ForeignRecordingError``
topics     ``parse_topic`` (kind and ids of a topic), ``SeqTracker`` (sequence gaps)
schemas    ``SchemaRegistry``: the JSON Schema of each channel
writer     ``McapSink``: what the recorder service writes with (``SplitPolicy``: parts)
reader     ``McapScanner``: sequential, damage-tolerant reading; ``side_records``
           (metadata and attachments wherever they are in the file)
repair     ``recover``: a truncated file -> a valid, indexed one
outputs    ``check_output`` (never over an input), ``atomic_path`` (temp file + rename)
summary    ``summarize``, ``validate_file`` (against ``schemas/``): ``diffpos inspect``
========== =====================================================================

A shared layer (the recorder writes, the dashboard and replay read); the offline re-run of a
recording is the replay service, :mod:`diffpos_services.replay`. Key expressions and MCAP
topics are spelled in :mod:`diffpos_services.wire.keys` only.
"""
