"""`midas export` of long sessions: time, peak memory and file size per format (issue 15), 10 and 60 minutes.

The session is aligned (`midas align`, untimed) before the exports: the LeRobot export reads the aligned
table (and Parquet then writes aligned.parquet too).

The session is bench_align's (EmHT 4 x 240 Hz, FPS 9 ch x 250 Hz, HandKP 30 Hz, 30 fps video clock,
random-walk values), written through the session writer and finalised like a recording. Each format runs
alone in a fresh `python -m midas_cli export SESSION --format F --out DIR` child: wall seconds of the
whole process and the child's own peak resident memory (VmHWM, read at its exit). Memory should not
grow with session length: streams are read and written a piece at a time.

    .venv/bin/python benchmarks/bench_export.py            # 10 and 60 min -> results/export.json
    .venv/bin/python benchmarks/bench_export.py --quick    # 2 min
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_align import write_session  # noqa: E402
from machine import load_average, machine_info, write_result  # noqa: E402

FORMATS = ("mcap", "parquet", "xdf", "lerobot")  # lerobot reads the aligned table: `midas align` runs first
WRAPPER = r"""
import atexit, sys
result_file = sys.argv[1]
sys.argv = ["midas", *sys.argv[2:]]

def report():
    hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM:")][0].split()[1]
    open(result_file, "w").write(hwm)

atexit.register(report)
from midas_cli.__main__ import main
main()
"""


def export_once(session: Path, fmt: str, out: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        hwm_file = Path(tmp) / "hwm"
        t0 = time.monotonic()
        result = subprocess.run([sys.executable, "-c", WRAPPER, str(hwm_file), "export", str(session), "--format", fmt,
                                 "--out", str(out)], capture_output=True, text=True)
        wall = time.monotonic() - t0
        if result.returncode != 0:
            raise RuntimeError(f"export {fmt} failed: {result.stderr[-2000:]}")
        peak_kib = int(hwm_file.read_text())
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"wall_s": round(wall, 2), "peak_rss_mib": round(peak_kib / 1024, 1), "output_mb": round(size / 1e6, 1),
            "load_average_after": load_average()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one 2-minute session")
    args = parser.parse_args()
    sizes = [2.0] if args.quick else [10.0, 60.0]
    load_before = load_average()
    runs = []
    for minutes in sizes:
        with tempfile.TemporaryDirectory(prefix="midas-bench-export-") as tmp:
            session = write_session(Path(tmp) / "sessions", minutes)
            csv_mb = sum(p.stat().st_size for p in (session / "streams").glob("*.csv")) / 1e6
            subprocess.run([sys.executable, "-m", "midas_cli", "align", str(session)], check=True, capture_output=True)
            formats = {}
            for fmt in FORMATS:
                out = Path(tmp) / f"out-{fmt}"
                formats[fmt] = export_once(session, fmt, out)
                shutil.rmtree(out)
            runs.append({"minutes": minutes, "stream_csv_mb": round(csv_mb, 1), "formats": formats})
    write_result("export", {"machine": machine_info(), "quick": args.quick,
                            "load_average_1min_before_after": [load_before, load_average()], "runs": runs})


if __name__ == "__main__":
    main()
