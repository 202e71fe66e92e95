"""A session as an MCAP file (https://mcap.dev/spec), written with the ``mcap`` library.

* one channel per stream, topic ``/<stream>``, JSON messages (one per CSV row, every column; a missing
  value is ``null``) with a JSON Schema (``jsonschema`` encoding) whose properties carry each column's
  unit, dtype and description from the manifest; ``log_time`` = ``publish_time`` = ``t_host_ns`` and
  ``sequence`` = ``seq`` (mod 2**32);
* the frame clock is the ``/video`` channel (its ``seq`` is the frame index labels count in); each label
  set is a channel ``/labels/<name>`` (``{"frame", "label"}``, one message per labelled frame, ``log_time``
  = that frame's ``t_host_ns``);
* the manifest is the metadata record ``midas.manifest`` (key ``manifest.json``, the JSON text), each
  label set's JSON the record ``midas.labels.<name>``.

Foxglove opens it (JSON messages with a JSON Schema); note that JavaScript numbers hold ``t_host_ns``
only to about 256 ns: the exact time of a message is its ``log_time``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from midas_cli import __version__
from midas_cli.interop.common import FRAME_STREAM, column_facts, frame_clock, json_columns, label_sets
from midas_cli.session.outputs import replacing
from midas_cli.session.reader import Session

JSON_TYPES = {"int": "integer", "float": "number", "text": "string"}


def stream_schema(session: Session, name: str) -> dict[str, Any]:
    spec = session.stream_spec(name)
    properties = {}
    for column in column_facts(session, name):
        nullable = column["name"] not in ("seq", "t_host_ns")
        kind = JSON_TYPES.get(column["dtype"], "number")
        properties[column["name"]] = {"type": [kind, "null"] if nullable else kind, **{
            k: v for k, v in column.items() if k != "name"}}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"midas.{name}",
            "description": spec.description, "type": "object", "properties": properties,
            "required": list(properties)}


def write_mcap(session: Session, target: Path) -> dict[str, Any]:
    """Write ``target`` (.mcap); returns what was written (messages per topic)."""
    from mcap.writer import CompressionType, Writer

    counts: dict[str, int] = {}
    with replacing(target) as tmp, open(tmp, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"midas {__version__}")
        for name in session.stream_names:
            schema = stream_schema(session, name)
            schema_id = writer.register_schema(name=schema["title"], encoding="jsonschema",
                                               data=json.dumps(schema).encode())
            entry = session.manifest["streams"][name]
            channel_meta = {"midas.stream": name, "nominal_rate_hz": str(entry.get("nominal_rate_hz")),
                            "units": json.dumps({c["name"]: c.get("unit", "") for c in schema_meta(schema)})}
            if name == FRAME_STREAM:
                channel_meta["frame_clock"] = "true"
            channel_id = writer.register_channel(topic=f"/{name}", message_encoding="json", schema_id=schema_id,
                                                 metadata=channel_meta)
            counts[f"/{name}"] = 0
            for chunk in session.iter_stream(name):
                names = list(chunk.columns)
                seq_at, time_at = names.index("seq"), names.index("t_host_ns")
                for row in zip(*json_columns(chunk)):
                    t = row[time_at]
                    writer.add_message(channel_id, log_time=t, publish_time=t, sequence=row[seq_at] & 0xFFFFFFFF,
                                       data=json.dumps(dict(zip(names, row)), separators=(",", ":")).encode())
                counts[f"/{name}"] += len(chunk)
        _write_labels(session, writer, counts)
        writer.add_metadata("midas.manifest", {"manifest.json": json.dumps(session.manifest)})
        writer.finish()
    return {"file": str(target), "messages": counts}


def schema_meta(schema: dict[str, Any]) -> list[dict[str, Any]]:
    return [{"name": k, **v} for k, v in schema["properties"].items()]


def _write_labels(session: Session, writer: Any, counts: dict[str, int]) -> None:
    sets = list(label_sets(session, frame_clock(session)))
    if not sets:
        return
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "midas.labels", "type": "object",
              "description": "one label per video frame ('' = unlabelled)",
              "properties": {"frame": {"type": "integer", "unit": "count",
                                       "description": f"0-based frame index = seq of the {FRAME_STREAM} stream"},
                             "label": {"type": "string"}}, "required": ["frame", "label"]}
    schema_id = writer.register_schema(name="midas.labels", encoding="jsonschema", data=json.dumps(schema).encode())
    for labels in sets:
        topic = f"/labels/{labels.name}"
        channel_id = writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id,
                                             metadata={"midas.labels": labels.name, "frame_clock": f"/{FRAME_STREAM}"})
        for k, (frame, label, t) in enumerate(zip(labels.frames.tolist(), labels.labels.tolist(),
                                                 labels.t_host_ns.tolist())):
            writer.add_message(channel_id, log_time=t, publish_time=t, sequence=k & 0xFFFFFFFF,
                               data=json.dumps({"frame": frame, "label": str(label)}).encode())
        counts[topic] = len(labels.frames)
        writer.add_metadata(f"midas.labels.{labels.name}", {"labels.json": json.dumps(labels.meta, default=str)})
