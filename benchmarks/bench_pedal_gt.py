"""Speed of `midas ground-truth pedals` on synthetic da Vinci Xi console videos (not a test).

Renders seeded videos with `midas simulate console-video`'s generator (1080p single view, and a
side-by-side stereo recording of two 1080p views as OBS writes it), then measures on this machine:
decoding alone (grab + retrieve of every frame), full extraction (decode + the davinci-xi layout), and
two videos at once with --jobs 1 and 2. Speeds are frames per second and multiples of real time
(30 fps). Agreement with the rendered schedule is recorded too. Results: benchmarks/results/pedal_gt.json.

    .venv/bin/python benchmarks/bench_pedal_gt.py [--duration 30] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import cv2
import pandas as pd

from midas_cli.analysis.pedal_video.agreement import compare
from midas_cli.analysis.pedal_video.extract import extract_pedal_states
from midas_cli.analysis.pedal_video.ground_truth import GroundTruthRequest, run_many
from midas_cli.analysis.pedal_video.layout import load_layout
from midas_cli.analysis.pedal_video.synthetic import ConsoleVideoSpec, render_console_video

REAL_TIME_FPS = 30.0
RESULTS = Path(__file__).resolve().parent / "results" / "pedal_gt.json"


def decode_fps(path: Path) -> float:
    """Frames per second of decoding alone: grab + retrieve (BGR conversion) of every frame."""
    capture, frames, started = cv2.VideoCapture(str(path)), 0, time.perf_counter()
    while capture.grab():
        capture.retrieve()
        frames += 1
    capture.release()
    return frames / (time.perf_counter() - started)


def measure_video(folder: Path, name: str, spec: ConsoleVideoSpec) -> dict:
    started = time.perf_counter()
    video = render_console_video(folder / f"{name}.mkv", spec)
    render_s = time.perf_counter() - started
    decode = decode_fps(video.video)
    started = time.perf_counter()
    states = extract_pedal_states(video.video, load_layout("davinci-xi"))
    extract_s = time.perf_counter() - started
    schedule = pd.read_csv(video.schedule_csv)
    agreement = [compare(p, states.column(p), schedule[p].to_numpy()) for p in states.pedals]
    fps = video.frames / extract_s
    return {"video": name, "frame_size": [states.video.width, states.video.height], "view": states.view,
            "frames": video.frames, "file_mb": round(video.video.stat().st_size / 1e6, 1),
            "render_fps": round(video.frames / render_s, 1), "decode_only_fps": round(decode, 1),
            "extract_fps": round(fps, 1), "x_real_time": round(fps / REAL_TIME_FPS, 2),
            "min_f1": round(min(a.f1 for a in agreement), 4),
            "max_onset_error_frames": max((a.max_onset_error or 0) for a in agreement)}


def measure_jobs(folder: Path, video: Path) -> dict:
    """Two copies of one video, processed with --jobs 1 and --jobs 2: aggregate frames per second."""
    copies = [shutil.copy(video, folder / f"copy{i}.mkv") for i in (1, 2)]
    result = {}
    for jobs in (1, 2):
        started = time.perf_counter()
        outcomes = run_many([GroundTruthRequest(Path(c)) for c in copies], jobs)
        frames = sum(o.frames for o in outcomes)
        result[f"jobs_{jobs}_fps"] = round(frames / (time.perf_counter() - started), 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of video per case")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cases = [measure_video(folder, "mono_1080p", ConsoleVideoSpec(args.duration, args.seed)),
                 measure_video(folder, "stereo_2x1080p", ConsoleVideoSpec(args.duration, args.seed, stereo=True))]
        jobs = measure_jobs(folder, folder / "mono_1080p.mkv")
    report = {"benchmark": "midas ground-truth pedals (davinci-xi layout, mp4v in MKV)",
              "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                          "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
                          "load_average_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)]},
              "real_time_fps": REAL_TIME_FPS, "cases": cases, "two_videos_mono_1080p": jobs}
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
