"""A session as Parquet files (pyarrow): ``<out>/<session_id>/``

* ``<stream>.parquet`` for every stream: the CSV's columns with the dtypes ``Session.read_stream`` gives
  (int64 ``seq``/``t_host_ns``, nullable Int64 for other int columns, float64 with NaN = missing, string
  for text), written a piece at a time (one row group per piece); ``pandas.read_parquet`` gives exactly the
  CSV's values. Types come from the stream's declared columns, never from its content (a stream whose text
  column is empty is still ``string``), so files of many sessions read as one table. Each field's metadata
  holds its unit, dtype and description; the schema metadata holds ``midas.manifest`` (the whole
  manifest), ``midas.stream`` (the stream's entry), ``midas.units`` and ``midas.sync`` (the session's sync
  statement, session/sync_statement.py);
* every file ends with the session's columns ``session_id``, ``subject``, ``task`` (strings) and ``trial``
  (int64), the same on every row (null where the manifest lacks them; dictionary-encoded, so nearly free),
  so ``read_parquet('DIR/*/emht.parquet')`` in DuckDB, polars or pyarrow tells sessions apart;
* ``labels_<name>.parquet`` for every label set: ``frame``, ``label`` (as the CSV) and ``t_host_ns`` (the
  frame's host time, null where the video stream lacks the frame), the set's JSON in ``midas.labels``;
* ``aligned.parquet`` when ``midas align`` has run: ``frame``, ``t_host_ns`` and every aligned column
  (float64, NaN = masked), ``aligned.json`` in ``midas.aligned``.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.interop.common import column_facts, frame_clock
from midas_cli.session.derived import read_aligned
from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.outputs import out_child, replacing
from midas_cli.session.reader import Session
from midas_cli.session.sync_statement import statement

ALIGNED_ROWS = 65536  # rows per row group of aligned.parquet
SESSION_COLUMNS = ("session_id", "subject", "task", "trial")  # appended to every file's rows
ARROW_TYPES = {"int": "int64", "float": "float64", "text": "string"}  # a stream column's dtype -> Arrow type


def _meta(document: Any) -> bytes:
    return json.dumps(document, default=str).encode()


def session_values(manifest: dict[str, Any]) -> dict[str, Any]:
    """The values of ``SESSION_COLUMNS`` for one session (subject as text: manifests hold ints or strings)."""
    metadata = manifest.get("metadata") or {}
    subject, task, trial = metadata.get("subject"), metadata.get("task"), metadata.get("trial")
    return {"session_id": manifest["session_id"], "subject": None if subject is None else str(subject),
            "task": None if task is None else str(task), "trial": trial if isinstance(trial, int) else None}


def _session_fields() -> list[Any]:
    import pyarrow as pa

    return [pa.field("session_id", pa.string()), pa.field("subject", pa.string()),
            pa.field("task", pa.string()), pa.field("trial", pa.int64())]


def _session_arrays(values: dict[str, Any], rows: int) -> list[Any]:
    """The session columns for ``rows`` rows: each a constant, dictionary-friendly array."""
    import pyarrow as pa

    return [pa.array([values[name]] * rows, field.type) for name, field in zip(SESSION_COLUMNS, _session_fields())]


def _pandas_metadata(head: Any) -> bytes:
    """pandas' own schema note for a stream piece plus the session columns, so ``pandas.read_parquet``
    restores the reader's dtypes (nullable Int64 for int columns)."""
    import pandas as pd
    import pyarrow as pa

    empty = head.iloc[:0].assign(session_id=pd.Series(dtype=object), subject=pd.Series(dtype=object),
                                 task=pd.Series(dtype=object), trial=pd.Series(dtype="Int64"))
    return pa.Schema.from_pandas(empty, preserve_index=False).metadata[b"pandas"]


def _stream_schema(session: Session, name: str, head: Any) -> Any:
    """The Arrow schema of one stream's file, from its declared columns (never from what a piece holds;
    ``head``, a parsed piece, only gives pandas' note of its dtypes)."""
    import pyarrow as pa

    facts = {c["name"]: c for c in column_facts(session, name)}
    fields = [pa.field(column.name, ARROW_TYPES[column.dtype], nullable=column.name not in ("seq", "t_host_ns"))
              .with_metadata({k: str(v) for k, v in facts[column.name].items()})
              for column in session.stream_spec(name).columns]
    clash = sorted(set(SESSION_COLUMNS) & set(facts))
    if clash:
        raise ValueError(f"stream {name} has a column named {clash[0]}, which Parquet export adds per session")
    return pa.schema(fields + _session_fields(), metadata={
        b"pandas": _pandas_metadata(head), b"midas.sync": _meta(statement(session.path, session.manifest)),
        b"midas.manifest": _meta(session.manifest),
        b"midas.stream": _meta({"name": name, **session.manifest["streams"][name]}),
        b"midas.units": _meta({k: v.get("unit", "") for k, v in facts.items()})})


def _stream_table(chunk: Any, schema: Any, values: dict[str, Any]) -> Any:
    """One parsed piece of a stream as an Arrow table of ``schema`` (the session columns appended)."""
    import pyarrow as pa

    stream_fields = [field for field in schema if field.name not in SESSION_COLUMNS]
    arrays = [pa.array(chunk[field.name], field.type, from_pandas=True) for field in stream_fields]
    return pa.Table.from_arrays(arrays + _session_arrays(values, len(chunk)), schema=schema)


def write_parquet(session: Session, folder: Path) -> dict[str, Any]:
    """Write the files above into ``folder`` (existing); returns rows per file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows: dict[str, int] = {}
    values = session_values(session.manifest)
    for name in session.stream_names:
        chunks = session.iter_stream(name)  # at least one piece, empty for a stream without rows
        first = next(chunks)
        schema = _stream_schema(session, name, first)
        target = out_child(folder, f"{name}.parquet")
        rows[target.name] = 0
        with replacing(target) as tmp, pq.ParquetWriter(tmp, schema) as writer:
            for chunk in itertools.chain([first], chunks):
                writer.write_table(_stream_table(chunk, schema, values))
                rows[target.name] += len(chunk)
    clock = frame_clock(session)
    for name in list_label_sets(session.path):
        labels = read_frame_labels(session.path, name)
        times = clock.times_of(labels.frames) if clock is not None else np.full(len(labels.frames), -1)
        table = pa.table({"frame": pa.array(labels.frames, pa.int64()),
                          "label": pa.array([str(v) for v in labels.labels], pa.string()),
                          "t_host_ns": pa.array(times, pa.int64(), mask=times < 0)})
        for field, array in zip(_session_fields(), _session_arrays(values, table.num_rows)):
            table = table.append_column(field, array)
        table = table.replace_schema_metadata({b"midas.labels": _meta(labels.meta),
                                               b"midas.manifest": _meta(session.manifest)})
        target = out_child(folder, f"labels_{name}.parquet")
        with replacing(target) as tmp:
            pq.write_table(table, tmp)
        rows[target.name] = table.num_rows
    if (session.path / "derived" / "aligned.npz").is_file():
        rows["aligned.parquet"] = _write_aligned(session, folder / "aligned.parquet")
    return {"folder": str(folder), "rows": rows}


def _write_aligned(session: Session, target: Path) -> int:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = read_aligned(session.path)  # values memory-mapped: read a row group at a time
    fields = [pa.field("frame", pa.int64()), pa.field("t_host_ns", pa.int64())]
    fields += [pa.field(c, pa.float64()) for c in table.columns] + _session_fields()
    session_row = session_values(session.manifest)
    schema = pa.schema(fields, metadata={b"midas.aligned": _meta(table.meta),
                                         b"midas.manifest": _meta(session.manifest)})
    with replacing(target) as tmp, pq.ParquetWriter(tmp, schema) as writer:
        for start in range(0, max(len(table.frame), 1), ALIGNED_ROWS):
            stop = start + ALIGNED_ROWS
            values = np.asarray(table.values[start:stop], dtype=np.float64)
            arrays = [pa.array(np.asarray(table.frame[start:stop], np.int64)),
                      pa.array(np.asarray(table.t_host_ns[start:stop], np.int64))]
            arrays += [pa.array(values[:, k]) for k in range(values.shape[1])]
            arrays += _session_arrays(session_row, len(arrays[0]))
            writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
    return int(len(table.frame))
