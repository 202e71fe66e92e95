"""`midas align` vs a per-stream pandas ``merge_asof`` baseline (CSV in, CSV out), 10, 30 and 60 min sessions.

A session (EmHT 4 sensors x 240 Hz, FPS 9 channels x 250 Hz, HandKP 30 Hz, 30 fps video clock, random-walk
values, < 1 ms jitter) is written through midas_cli/session/writer.py with vectorised CSV formatting and
finalised like a recording (so it has its binary stream copies). Each side runs in a fresh child
process, three times (the median is kept): ``work_s`` from the first file read to the aligned output on
disk (after imports), ``process_s`` the whole child, and its peak resident memory. midas also runs once
with ``--csv`` and once with the binary copies moved away (parsing the CSVs). Then every raw
``<stream>.<column>`` value the two produce for EmHT, FPS and HandKP is compared (same frames masked,
values within 1e-9 relative).

    .venv/bin/python benchmarks/bench_align.py            # 10, 30, 60 min -> results/align.json
    .venv/bin/python benchmarks/bench_align.py --quick    # 2 min, one repeat
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

from midas_cli.clock import HostClock  # noqa: E402
from midas_cli.devices.registry import describe_device  # noqa: E402
from midas_cli.session.writer import SessionMetadata, SessionWriter  # noqa: E402

URLS = {"video": "sim://video?rate=30", "emht": "sim://emht?rate=240&sensors=4",
        "handkp": "sim://handkp?rate=30", "fps": "sim://fps?rate=250&channels=9"}
RATES = {"video": 30.0, "emht": 240.0, "handkp": 30.0, "fps": 250.0}
COMPARED = ("emht", "fps", "handkp")
STALE_PERIODS = 3.0  # midas align's default: a sample more than 3 nominal periods old is masked
CHUNK = 20_000
START_NS = 1_800_000_000 * 10**9

BASELINE = r'''
import sys, pandas as pd
session, out, stale = sys.argv[1], sys.argv[2], float(sys.argv[3])
rates = {"emht": 240.0, "fps": 250.0, "handkp": 30.0}
merged = pd.read_csv(f"{session}/streams/video.csv")[["seq", "t_host_ns"]].rename(columns={"seq": "frame"})
for name, rate in rates.items():
    df = pd.read_csv(f"{session}/streams/{name}.csv").sort_values("t_host_ns")
    df = df.rename(columns={c: f"{name}.{c}" for c in df.columns if c != "t_host_ns"})
    df[f"{name}.t_host_ns"] = df["t_host_ns"]
    merged = pd.merge_asof(merged, df, on="t_host_ns", direction="backward", tolerance=int(stale * 1e9 / rate))
merged.to_csv(out, index=False)
'''


def write_session(root: Path, minutes: float, seed: int = 1) -> Path:
    """A session of ``minutes`` with every stream at its full rate; returns the folder."""
    rng = np.random.default_rng(seed)
    specs = {name: describe_device(name, url).streams[0] for name, url in URLS.items()}
    devices = {name: {"kind": name, "url": url, "settings": {}, "streams": [name]} for name, url in URLS.items()}
    writer = SessionWriter.create(root, SessionMetadata("1", "bench", 1), HostClock(START_NS - 10**12), devices,
                                  list(specs.values()), {"generator": "benchmarks/bench_align.py"}, start_ns=START_NS)
    for name, spec in specs.items():
        n = int(minutes * 60 * RATES[name])
        k = np.arange(n, dtype=np.int64)
        host = START_NS + np.round(k * 1e9 / RATES[name] + rng.uniform(0, 1e6, n)).astype(np.int64)
        for begin in range(0, n, CHUNK):
            end = min(n, begin + CHUNK)
            writer.append(name, format_chunk(spec, k[begin:end], host[begin:end], rng))
    writer.finalize("complete", "benchmark", int(host[-1]) + 50_000_000, {})
    return writer.folder


def format_chunk(spec, k: np.ndarray, host: np.ndarray, rng: np.random.Generator) -> str:
    """CSV text for rows k with random values, formatted per column like StreamSpec.format_rows."""
    columns = [k.astype(str), host.astype(str)]
    for column in spec.columns[2:]:
        if column.dtype == "int":
            values = rng.integers(0, 2 if column.unit == "bool" else 1024, len(k))  # flags (pressed, detected): 0/1
            columns.append(values.astype(str))
        else:
            values = np.cumsum(rng.normal(0, 0.5, len(k))) + 100.0
            if column.name.endswith("_mm") and spec.name == "handkp":
                values[rng.random(len(k)) < 0.02] = np.nan
            text = np.char.mod(f"%.{column.decimals}f", values)
            columns.append(np.where(np.isnan(values), "", text))
    lines = columns[0]
    for c in columns[1:]:
        lines = np.char.add(np.char.add(lines, ","), c)
    return "\n".join(lines.tolist()) + "\n"


WORK_WRAPPER = r"""
import json, runpy, sys, time
result_file, side, *args = sys.argv[1:]
if side == "baseline":
    import pandas  # noqa: F401 - the baseline's only import, loaded before the clock starts
    script, session, out, stale = args
    sys.argv = [script, session, out, stale]
    t0 = time.perf_counter()
    runpy.run_path(script, run_name="__main__")
else:
    from midas_cli.analysis.align import AlignOptions, align_and_write
    import scipy.linalg  # noqa: F401 - imported lazily by align's gap filling: an import, not work
    session, csv = args
    t0 = time.perf_counter()
    align_and_write(session, AlignOptions(), csv=csv == "csv")
work = time.perf_counter() - t0
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM:")][0].split()[1]
json.dump({"work_s": work, "peak_kib": int(hwm)}, open(result_file, "w"))
"""


def timed(side: str, args: list[str]) -> dict:
    """Run one side in a fresh child: ``work_s`` = from the first file read to the output on disk (after
    its imports: the baseline's pandas, midas's align module), ``process_s`` = the whole child including
    interpreter start-up and imports, and the child's own peak RSS (VmHWM, MiB: per process image, so
    not inherited from this parent the way ru_maxrss is across fork/exec)."""
    with tempfile.TemporaryDirectory() as tmp:
        result_file, log_file = Path(tmp) / "result.json", Path(tmp) / "log"
        t0 = time.monotonic()
        with open(log_file, "wb") as log:
            code = subprocess.call([sys.executable, "-c", WORK_WRAPPER, str(result_file), side, *args],
                                   stdout=subprocess.DEVNULL, stderr=log)
        process_s = time.monotonic() - t0
        if code != 0:
            raise RuntimeError(f"{side} {args} failed: {log_file.read_text(errors='replace')[-2000:]}")
        result = json.loads(result_file.read_text())
    return {"work_s": round(result["work_s"], 3), "process_s": round(process_s, 2),
            "peak_rss_mib": round(result["peak_kib"] / 1024, 1), "load_average_after": load_average()}


def repeated(side: str, args: list[str], repeats: int, outputs: list[Path]) -> dict:
    """``timed`` ``repeats`` times; the run with the median work time, plus every work time. Each run
    starts with no output on disk (``outputs`` deleted first), like a first run: replacing a file
    makes ext4 flush the new one early (auto_da_alloc), which would time the disk, not the code."""
    runs = []
    for _ in range(repeats):
        remove(outputs)
        runs.append(timed(side, args))
    runs.sort(key=lambda r: r["work_s"])
    return {**runs[len(runs) // 2], "work_s_all": [r["work_s"] for r in runs], "repeats": repeats}


def compare(session: Path, baseline_csv: Path) -> dict:
    """Every raw <stream>.<column> of COMPARED streams: same mask, equal values (rtol 1e-9)."""
    from midas_cli.session.derived import read_aligned

    table = read_aligned(session)
    columns, values, mask = table.columns, table.values, table.mask
    base = pd.read_csv(baseline_csv)
    compared, mismatched, mask_diff = 0, [], 0
    for i, name in enumerate(columns):
        stream = name.split(".", 1)[0]
        if stream not in COMPARED or name not in base.columns:
            continue
        ref = base[name].to_numpy(dtype=float)
        ok = mask[:, i]
        mask_diff += int(np.sum(ok != ~np.isnan(ref)))
        both = ok & ~np.isnan(ref)
        if not np.allclose(values[both, i], ref[both], rtol=1e-9, atol=0):
            mismatched.append(name)
        compared += 1
    return {"columns_compared": compared, "frames": int(len(base)), "midas_columns": len(columns) + 2,
            "baseline_columns": int(len(base.columns)), "mismatched_columns": mismatched,
            "mask_disagreements": mask_diff, "equal": not mismatched and mask_diff == 0,
            "rule": "raw <stream>.<column> of emht, fps, handkp (seq, t_host_ns, device time, values); a frame is "
                    "masked in midas iff the baseline left it empty (merge_asof backward, tolerance 3 periods); "
                    "unmasked values equal within rtol 1e-9"}


STAGES = {"read_streams": "open the stream copies (memory-map)", "reference_frames": "read video frame clock",
          "add_raw_streams": "associate raw streams with frames (reads the chosen rows)",
          "add_emht_features": "EmHT hand points/velocity", "add_handkp_features": "HandKP gap filling",
          "in_parallel": "EmHT + HandKP features (two threads)", "add_robot_orientation": "robot orientation",
          "add_clutch": "clutch", "build_table": "build table",
          "write_aligned": "write aligned.npz, .values.npy, .json"}


def profile_align(session: Path) -> dict:
    """cProfile of align_and_write in this process (the work `midas align` does after start-up) and the
    CLI's start-up (``python -m midas_cli --help``)."""
    import cProfile
    import pstats

    from midas_cli.analysis.align import AlignOptions, align_and_write

    profiler = cProfile.Profile()
    t0 = time.monotonic()
    profiler.runcall(align_and_write, session, AlignOptions())
    total = time.monotonic() - t0
    stats = pstats.Stats(profiler).stats
    stages = {}
    for (file, _, function), v in stats.items():
        if function in STAGES and "midas_cli" in file:
            stages[STAGES[function]] = round(stages.get(STAGES[function], 0.0) + v[3], 3)
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "midas_cli", "--help"], capture_output=True, check=True)
    return {"align_and_write_s_profiled": round(total, 3), "stages_cumulative_s": stages,
            "cli_startup_s": round(time.monotonic() - t0, 2)}


def run_size(minutes: float, profile: bool = False, repeats: int = 3) -> dict:
    with tempfile.TemporaryDirectory(prefix="midas-bench-align-") as tmp:
        t0 = time.monotonic()
        made = subprocess.run([sys.executable, __file__, "--generate", tmp, str(minutes)], check=True,
                              capture_output=True, text=True)  # keeps this process small (see timed)
        session = Path(made.stdout.strip().splitlines()[-1])
        generate_s = time.monotonic() - t0
        size_mb = sum(p.stat().st_size for p in (session / "streams").glob("*.csv")) / 1e6
        copies_s = time_binary_copies(session)
        copies_mb = sum(p.stat().st_size for p in (session / "streams").glob("*.npy")) / 1e6
        baseline_csv = Path(tmp) / "baseline.csv"
        script = Path(tmp) / "baseline_merge_asof.py"
        script.write_text(BASELINE, encoding="utf-8")
        aligned = [session / "derived" / f"aligned.{ext}" for ext in ("npz", "values.npy", "json", "csv")]
        base = repeated("baseline", [str(script), str(session), str(baseline_csv), str(STALE_PERIODS)], repeats,
                        [baseline_csv])
        with_csv = repeated("midas", [str(session), "csv"], 1, aligned)
        from_csv = without_copies(session, lambda: repeated("midas", [str(session), "npz"], 1, aligned))
        midas = repeated("midas", [str(session), "npz"], repeats + 2, aligned)
        output_mb = sum(p.stat().st_size for p in (session / "derived").glob("aligned.*")) / 1e6
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "midas_cli", "align", str(session), "--json"], check=True,
                       capture_output=True)
        cli_s = time.monotonic() - t0
        check = compare(session, baseline_csv)
        where = profile_align(session) if profile else None
    return {"minutes": minutes, "stream_csv_mb": round(size_mb, 1), "stream_copies_mb": round(copies_mb, 1),
            "aligned_output_mb": round(output_mb, 1), "generate_s": round(generate_s, 1),
            "binary_copies_at_finalise_s": copies_s,
            "baseline_merge_asof": base, "midas_align": midas, "midas_align_csv_too": with_csv,
            "midas_align_from_csv": from_csv, "midas_cli_process_s": round(cli_s, 2),
            "speedup_work": round(base["work_s"] / midas["work_s"], 1),
            "speedup_process": round(base["process_s"] / midas["process_s"], 1),
            "speedup_from_csv": round(base["work_s"] / from_csv["work_s"], 1), "check": check, "profile": where}


def remove(paths: list[Path]) -> None:
    """Delete earlier outputs and flush the page cache's dirty pages, so no run pays for the writeback
    of what ran before it."""
    for path in paths:
        path.unlink(missing_ok=True)
    os.sync()


def time_binary_copies(session: Path) -> float:
    """Seconds to (re)write every binary stream copy, as finalise does when a recording stops: the cost
    moved from every `midas align` to the end of the recording."""
    from midas_cli.session.columnar import add_binary_copies
    from midas_cli.session.manifest import load_manifest

    t0 = time.monotonic()
    add_binary_copies(session, load_manifest(session))
    return round(time.monotonic() - t0, 2)


def without_copies(session: Path, body):  # noqa: ANN001, ANN201
    """Run ``body`` with the session's binary copies moved aside (align then parses the CSVs)."""
    copies = sorted((session / "streams").glob("*.npy"))
    for path in copies:
        path.rename(path.with_suffix(".npy.off"))
    try:
        return body()
    finally:
        for path in copies:
            path.with_suffix(".npy.off").rename(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one 2-minute session, one repeat")
    parser.add_argument("--minutes", type=float, nargs="+", default=[10.0, 30.0, 60.0])
    parser.add_argument("--generate", nargs=2, metavar=("ROOT", "MINUTES"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.generate:
        print(write_session(Path(args.generate[0]), float(args.generate[1])))
        return
    sizes = [2.0] if args.quick else args.minutes
    runs = []
    for minutes in sizes:
        print(f"align: {minutes:g} min session ...", file=sys.stderr)
        runs.append({"load_average_before": load_average(),
                     **run_size(minutes, profile=minutes == sizes[-1], repeats=1 if args.quick else 3)})
    slope = None
    if len(runs) >= 2:
        slope = {side: fit_slope([r["minutes"] for r in runs], [r[side]["work_s"] for r in runs])
                 for side in ("baseline_merge_asof", "midas_align", "midas_align_from_csv", "midas_align_csv_too")}
    write_result("align", {"machine": machine_info(), "quick": args.quick, "runs": runs,
                           "work_seconds_per_session_minute": slope})


def fit_slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of y against x (seconds per session minute)."""
    return round(float(np.polyfit(np.asarray(x), np.asarray(y), 1)[0]), 4)


if __name__ == "__main__":
    main()
