"""A session as an MCAP file (https://mcap.dev/spec) that Foxglove opens, written with ``foxglove-sdk``.

Topics (see :mod:`midas_cli.interop.foxglove_topics` for the schemas):

* ``/<stream>``: one JSON message per CSV row, single-typed fields, a missing value left out;
  ``/events`` (the operator's markers) as ``foxglove.Log``;
* ``/<stream>/transforms`` for streams with 6-DoF sensors (EmHT, the robot arms of ``mtm``/``psm``):
  metres, quaternions, frames ``<stream>/<sensor>`` in the position columns' frame;
* with ``with_video``: ``/<stream>/image`` (``foxglove.CompressedImage``, JPEG, frame id ``<stream>``)
  for each stream of RGB-D frames (columns ``file`` and ``frame`` into ``video/<device>_NNN.mkv``): one
  message per recorded frame, the side-by-side stereo pair as recorded, re-encoded as JPEG; and the
  console (endoscope) recording in ``video/`` as ``/video/h264`` (``foxglove.CompressedVideo``, H.264
  without B-frames, one message per frame on the frame clock; interop/mcap_video.py);
* ``/labels/<name>``: one JSON message ``{"label", "frame"}`` per labelled video frame, timed on the
  frame clock (the ``/video`` stream's ``seq`` is the frame index labels count in), for a
  state-transitions panel on ``/labels/<name>.label``.

Every message's ``log_time`` is its row's ``t_host_ns`` (the frame's, for labels). The manifest is
the metadata record ``midas.manifest`` (key ``manifest.json``), each label set's JSON the record
``midas.labels.<name>``. JavaScript numbers hold ``t_host_ns`` only to about 256 ns: the exact time of a
message is its ``log_time``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.interop.common import FRAME_STREAM, frame_clock, json_columns, label_sets
from midas_cli.interop.foxglove_topics import (json_row, marker_log, transforms_message,
                                               sensor_columns, sensor_poses, stream_json_schema,
                                               timestamp)
from midas_cli.interop.mcap_video import write_console_video
from midas_cli.record.markers import EVENTS_STREAM
from midas_cli.session.outputs import replacing
from midas_cli.session.reader import Session
from midas_cli.session.schema import StreamSpec

JPEG_QUALITY = 90

LABELS_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "midas.labels",
                 "type": "object", "description": "one label per video frame ('' = unlabelled)",
                 "properties": {"label": {"type": "string"},
                                "frame": {"type": "integer", "unit": "count",
                                          "description": f"0-based frame index = seq of the {FRAME_STREAM} stream"}},
                 "required": ["label", "frame"]}


def write_mcap(session: Session, target: Path, with_video: bool = False) -> dict[str, Any]:
    """Write ``target`` (.mcap); returns what was written (messages per topic). ``with_video`` adds the
    RGB-D frames as images (decoding and re-encoding every frame: it takes a while)."""
    import foxglove
    from foxglove.mcap import MCAPWriteOptions

    counts: dict[str, int] = {}
    context = foxglove.Context()  # channels of this file only (never a live server's)
    with replacing(target) as tmp:
        with foxglove.open_mcap(tmp, allow_overwrite=True, context=context,
                                writer_options=MCAPWriteOptions(profile="")) as writer:
            for name in session.stream_names:
                _write_stream(session, name, context, counts)
                if with_video and is_frame_stream(session.stream_spec(name)):
                    _write_images(session, name, context, counts)
            if with_video:
                write_console_video(session, context, counts)
            _write_labels(session, context, writer, counts)
            writer.write_metadata("midas.manifest", {"manifest.json": json.dumps(session.manifest)})
    return {"file": str(target), "messages": counts}


def _write_stream(session: Session, name: str, context: Any, counts: dict[str, int]) -> None:
    """The topics of stream ``name``, read a piece at a time."""
    from foxglove import Channel
    from foxglove.channels import FrameTransformsChannel, LogChannel

    spec = session.stream_spec(name)
    metadata = {"midas.stream": name, "nominal_rate_hz": str(spec.nominal_rate_hz),
                "units": json.dumps({c.name: c.unit for c in spec.columns})}
    if name == FRAME_STREAM:
        metadata["frame_clock"] = "true"
    is_markers = name == EVENTS_STREAM and {"text", "source"} <= set(spec.column_names)
    rows: Any = LogChannel(f"/{name}", context=context, metadata=metadata) if is_markers else \
        Channel(f"/{name}", schema=stream_json_schema(spec), context=context, metadata=metadata)
    sensors = sensor_columns(spec)
    transforms = FrameTransformsChannel(f"/{name}/transforms", context=context) if sensors else None
    counts[f"/{name}"] = 0
    for chunk in session.iter_stream(name):
        names, columns = list(chunk.columns), json_columns(chunk)
        times = chunk["t_host_ns"].to_numpy(np.int64).tolist()
        if is_markers:
            for t, text, source in zip(times, columns[names.index("text")], columns[names.index("source")]):
                rows.log(marker_log(t, text, source), log_time=t)
        else:
            for t, row in zip(times, zip(*columns)):
                rows.log(json_row(names, row), log_time=t)
        counts[f"/{name}"] += len(chunk)
        if sensors:
            _write_transforms(name, sensors, chunk, times, transforms, counts)


def _write_transforms(name: str, sensors: list, chunk: Any, times: list[int], channel: Any,
                      counts: dict[str, int]) -> None:
    """One FrameTransforms message per row of a piece of a 6-DoF stream."""
    table = {column: chunk[column].to_numpy(np.float64, na_value=np.nan)
             for sensor in sensors for column in sensor.position + sensor.orientation}
    counts.setdefault(channel.topic(), 0)
    for t, poses in zip(times, zip(*(sensor_poses(sensor, table) for sensor in sensors))):
        message = transforms_message(name, sensors, t, poses)
        if message is not None:
            channel.log(message, log_time=t)
            counts[channel.topic()] += 1


def is_frame_stream(spec: StreamSpec) -> bool:
    """True for a stream of RGB-D frames: rows point into the device's video files (``file``, ``frame``)."""
    return {"seq", "t_host_ns", "t_device_ns", "file", "frame"} == set(spec.column_names)


def _write_images(session: Session, name: str, context: Any, counts: dict[str, int]) -> None:
    """Every frame of RGB-D stream ``name`` as a JPEG ``foxglove.CompressedImage`` at its ``t_host_ns``."""
    import cv2
    from foxglove.channels import CompressedImageChannel
    from foxglove.messages import CompressedImage

    from midas_cli.analysis.handkp import iter_frames

    spec = session.stream_spec(name)
    channel = CompressedImageChannel(f"/{name}/image", context=context)
    counts[channel.topic()] = 0
    for _, t_ns, _, image in iter_frames(session, spec.device, session.read_stream(name)):
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise SessionError(f"{session.path}: a frame of {name} could not be encoded as JPEG")
        channel.log(CompressedImage(timestamp=timestamp(t_ns), frame_id=name, data=jpeg.tobytes(), format="jpeg"),
                    log_time=t_ns)
        counts[channel.topic()] += 1


def _write_labels(session: Session, context: Any, writer: Any, counts: dict[str, int]) -> None:
    """One topic per label set: its labelled frames at their host times."""
    from foxglove import Channel

    for labels in label_sets(session, frame_clock(session)):
        topic = f"/labels/{labels.name}"
        channel = Channel(topic, schema=LABELS_SCHEMA, context=context,
                          metadata={"midas.labels": labels.name, "frame_clock": f"/{FRAME_STREAM}"})
        for frame, label, t in zip(labels.frames.tolist(), labels.labels.tolist(), labels.t_host_ns.tolist()):
            channel.log({"label": str(label), "frame": frame}, log_time=t)
        counts[topic] = len(labels.frames)
        writer.write_metadata(f"midas.labels.{labels.name}", {"labels.json": json.dumps(labels.meta, default=str)})
