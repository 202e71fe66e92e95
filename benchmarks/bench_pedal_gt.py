"""Speed of `midas ground-truth pedals` on synthetic da Vinci Xi console videos (not a test).

Renders seeded videos with `midas simulate console-video`'s generator (720p and 1080p single view,
1080p again at twice the duration, and a side-by-side stereo recording of two 1080p views as OBS writes
it), then measures on this machine: decoding alone (grab + retrieve of every frame), full extraction
(decode + the davinci-xi layout), and two videos at once with --jobs 1 and 2. Speeds are frames per
second and multiples of real time (30 fps); the cost per frame is fitted against the decoded frame's
megapixels (µs per megapixel per frame) and compared between the two 1080p durations. Agreement with
the rendered schedule is recorded too. Results: benchmarks/results/pedal_gt.json.

    .venv/bin/python benchmarks/bench_pedal_gt.py [--duration 30] [--seed 1]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from midas_cli.analysis.pedal_video.agreement import compare
from midas_cli.analysis.pedal_video.extract import extract_pedal_states
from midas_cli.analysis.pedal_video.ground_truth import GroundTruthRequest, run_many
from midas_cli.analysis.pedal_video.layout import load_layout
from midas_cli.simulate.console_video import render_console_video
from midas_cli.synthetic.console_video import ConsoleVideoSpec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

REAL_TIME_FPS = 30.0


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


def pixel_slope(cases: list[dict]) -> dict:
    """Least-squares cost per frame against the decoded frame's megapixels, over the cases of one
    duration (µs per megapixel per frame; intercept = the per-frame cost that does not scale with pixels)."""
    frames = cases[0]["frames"]
    same = [c for c in cases if c["frames"] == frames]
    mp = np.array([c["frame_size"][0] * c["frame_size"][1] / 1e6 for c in same])
    result = {"cases": [c["video"] for c in same], "megapixels": mp.round(3).tolist()}
    for key in ("decode_only_fps", "extract_fps"):
        slope, intercept = np.polyfit(mp, [1e6 / c[key] for c in same], 1)
        result[key.replace("_fps", "")] = {"us_per_megapixel_per_frame": round(float(slope), 1),
                                           "intercept_us_per_frame": round(float(intercept), 1)}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of video per case")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    load_before = load_average()
    d, seed = args.duration, args.seed
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cases = [measure_video(folder, "mono_720p", ConsoleVideoSpec(d, seed, size=(1280, 720))),
                 measure_video(folder, "mono_1080p", ConsoleVideoSpec(d, seed)),
                 measure_video(folder, "stereo_2x1080p", ConsoleVideoSpec(d, seed, stereo=True)),
                 measure_video(folder, "mono_1080p_2x_frames", ConsoleVideoSpec(2 * d, seed))]
        jobs = measure_jobs(folder, folder / "mono_1080p.mkv")
    machine = {**machine_info(), "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
               "load_average_1min_before_after": [load_before, load_average()]}
    write_result("pedal_gt", {"benchmark": "midas ground-truth pedals (davinci-xi layout, mp4v in MKV)",
                              "date_utc": machine["date_utc"], "machine": machine, "real_time_fps": REAL_TIME_FPS,
                              "cases": cases, "pixel_slope": pixel_slope(cases),
                              "two_videos_mono_1080p": jobs})


if __name__ == "__main__":
    main()
