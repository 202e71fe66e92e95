"""A session as Parquet files (pyarrow): ``<out>/<session_id>/``

* ``<stream>.parquet`` for every stream: the CSV's columns with the dtypes ``Session.read_stream`` gives
  (int64 ``seq``/``t_host_ns``, nullable Int64 for other int columns, float64 with NaN = missing), written
  a piece at a time (one row group per piece); ``pandas.read_parquet`` gives exactly the CSV's values.
  Each field's metadata holds its unit, dtype and description; the schema metadata holds
  ``midas.manifest`` (the whole manifest), ``midas.stream`` (the stream's entry) and ``midas.units``;
* ``labels_<name>.parquet`` for every label set: ``frame``, ``label`` (as the CSV) and ``t_host_ns`` (the
  frame's host time, null where the video stream lacks the frame), the set's JSON in ``midas.labels``;
* ``aligned.parquet`` when ``midas align`` has run: ``frame``, ``t_host_ns`` and every aligned column
  (float64, NaN = masked), ``aligned.json`` in ``midas.aligned``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.interop.common import column_facts, frame_clock
from midas_cli.session.derived import read_aligned
from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.outputs import out_child, replacing
from midas_cli.session.reader import Session

ALIGNED_ROWS = 65536  # rows per row group of aligned.parquet


def _meta(document: Any) -> bytes:
    return json.dumps(document, default=str).encode()


def write_parquet(session: Session, folder: Path) -> dict[str, Any]:
    """Write the files above into ``folder`` (existing); returns rows per file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows: dict[str, int] = {}
    for name in session.stream_names:
        facts = {c["name"]: c for c in column_facts(session, name)}
        target = out_child(folder, f"{name}.parquet")
        rows[target.name] = 0
        with replacing(target) as tmp:
            writer = None
            try:
                for chunk in session.iter_stream(name):
                    if writer is None:
                        schema = pa.Schema.from_pandas(chunk, preserve_index=False)
                        schema = pa.schema([field.with_metadata({k: str(v) for k, v in facts[field.name].items()})
                                            for field in schema], metadata={
                            **schema.metadata, b"midas.manifest": _meta(session.manifest),
                            b"midas.stream": _meta({"name": name, **session.manifest["streams"][name]}),
                            b"midas.units": _meta({k: v.get("unit", "") for k, v in facts.items()})})
                        writer = pq.ParquetWriter(tmp, schema)
                    writer.write_table(pa.Table.from_pandas(chunk, schema=schema, preserve_index=False))
                    rows[target.name] += len(chunk)
            finally:
                if writer is not None:
                    writer.close()
    clock = frame_clock(session)
    for name in list_label_sets(session.path):
        labels = read_frame_labels(session.path, name)
        times = clock.times_of(labels.frames) if clock is not None else np.full(len(labels.frames), -1)
        table = pa.table({"frame": pa.array(labels.frames, pa.int64()),
                          "label": pa.array([str(v) for v in labels.labels], pa.string()),
                          "t_host_ns": pa.array(times, pa.int64(), mask=times < 0)})
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
    fields += [pa.field(c, pa.float64()) for c in table.columns]
    schema = pa.schema(fields, metadata={b"midas.aligned": _meta(table.meta),
                                         b"midas.manifest": _meta(session.manifest)})
    with replacing(target) as tmp, pq.ParquetWriter(tmp, schema) as writer:
        for start in range(0, max(len(table.frame), 1), ALIGNED_ROWS):
            stop = start + ALIGNED_ROWS
            values = np.asarray(table.values[start:stop], dtype=np.float64)
            arrays = [pa.array(np.asarray(table.frame[start:stop], np.int64)),
                      pa.array(np.asarray(table.t_host_ns[start:stop], np.int64))]
            arrays += [pa.array(values[:, k]) for k in range(values.shape[1])]
            writer.write_table(pa.Table.from_arrays(arrays, schema=schema))
    return int(len(table.frame))
