"""The endoscope (console) video as ``foxglove.CompressedVideo`` for the MCAP export (``--with-video``).

Foxglove plays H.264 in Annex B form, one message per frame, without B-frames (it does not look ahead),
each key frame carrying its SPS/PPS. A recording's own codec rarely fits that (OBS's x264 uses B-frames;
MJPG and others are not H.264 at all), so every recording is re-encoded with ffmpeg's libx264
(``-bf 0``, a key frame every second, ``aud=1:repeat-headers=1``, frames passed through 1:1) and the
Annex B stream is cut at its access unit delimiters: access unit k is frame k, stamped with the frame
clock's host time of frame k (the ``video`` stream's ``seq``, what labels count in). The stream is read
from ffmpeg's stdout a piece at a time: memory stays flat in the recording's length.
"""

from __future__ import annotations

import logging
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.interop.common import FRAME_STREAM, frame_clock
from midas_cli.interop.foxglove_topics import timestamp
from midas_cli.session.pedals_gt import session_videos
from midas_cli.session.reader import Session

log = logging.getLogger(__name__)

TOPIC = f"/{FRAME_STREAM}/h264"
FRAME_ID = "endoscope"
READ_BYTES = 1 << 20
_AUD = re.compile(b"\x00\x00\x01\x09")  # an access unit delimiter NAL (type 9): a new frame starts here


def encoder_command(video: Path, fps: float) -> list[str]:
    """ffmpeg writing ``video`` to stdout as Annex B H.264 Foxglove can play (see the module docstring)."""
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise ConfigError("--with-video needs ffmpeg for the console video (apt-get install ffmpeg)")
    return [ffmpeg, "-v", "error", "-nostdin", "-i", str(video), "-map", "0:v:0", "-an", "-fps_mode", "passthrough",
            "-c:v", "libx264", "-preset", "veryfast", "-pix_fmt", "yuv420p", "-bf", "0",
            "-g", str(max(1, int(round(fps)))), "-x264-params", "aud=1:repeat-headers=1", "-f", "h264", "-"]


def access_units(stream: Any) -> Iterator[bytes]:
    """The access units (one frame each, starting at their delimiter) of an Annex B byte stream."""
    pending = b""
    while True:
        block = stream.read(READ_BYTES)
        pending += block
        starts = [m.start() for m in _AUD.finditer(pending)]
        # a 4-byte start code puts one 0x00 before the 3-byte one: it belongs to the unit it starts
        starts = [s - 1 if s > 0 and pending[s - 1] == 0 else s for s in starts]
        if not block:
            bounds = starts + [len(pending)]
            yield from (pending[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a)
            return
        for a, b in zip(starts[:-1], starts[1:]):
            yield pending[a:b]
        if starts:
            pending = pending[starts[-1]:]


def write_console_video(session: Session, context: Any, counts: dict[str, int]) -> None:
    """The session's console recording(s) (``video/``), in order, as one ``CompressedVideo`` topic on the
    frame clock; a session without a recording or a frame clock gets a warning and no topic."""
    from foxglove.channels import CompressedVideoChannel
    from foxglove.messages import CompressedVideo

    videos, clock = session_videos(session.path), frame_clock(session)
    if not videos or clock is None:
        log.warning("%s: no console video to export (%s)", session.path,
                    "no recording in video/" if not videos else f"no {FRAME_STREAM!r} stream to time its frames")
        return
    fps = float(session.stream_spec(FRAME_STREAM).nominal_rate_hz or 30.0)
    channel = CompressedVideoChannel(TOPIC, context=context)
    frame = sent = 0
    for video in videos:
        process = subprocess.Popen(encoder_command(video, fps), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert process.stdout is not None
        for unit in access_units(process.stdout):
            t_ns = int(clock.times_of(np.array([frame]))[0])
            frame += 1
            if t_ns < 0:
                continue  # the frame clock lacks this frame (a dropped row): nothing to time it by
            channel.log(CompressedVideo(timestamp=timestamp(t_ns), frame_id=FRAME_ID, data=unit, format="h264"),
                        log_time=t_ns)
            sent += 1
        _, error = process.communicate()
        if process.returncode != 0:
            raise SessionError(f"{video}: ffmpeg could not re-encode it ({error.decode(errors='replace').strip()[-300:]})")
    if frame != len(clock.seq):
        log.warning("%s: the recording has %d frames, the %r stream %d", session.path, frame, FRAME_STREAM,
                    len(clock.seq))
    counts[TOPIC] = sent
