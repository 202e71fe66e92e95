"""Sessions out to other systems' files (`midas export`): MCAP, Parquet and XDF.

At the layer of the importers: each writer reads a session through ``session/reader.Session`` one piece
of a stream at a time (``Session.iter_stream``), so memory stays flat in the session's length, and writes
through ``session/outputs.py`` (a temporary beside the target, renamed into place).
"""
