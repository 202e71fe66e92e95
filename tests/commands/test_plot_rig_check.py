"""`midas plot` (the quick-look page) and `midas rig check|show` (pre-flight) (issue 15 items 4 and 6)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from helpers.cli import midas

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def simulated_session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dataset")
    midas("simulate", "dataset", "--trials", "1", "--max-seconds", "5", "--out", str(out), check=True)
    (session,) = [p for p in out.iterdir() if p.is_dir()]
    return session


def test_plot_draws_every_stream_and_the_label_ribbon(simulated_session: Path) -> None:
    result = midas("plot", str(simulated_session), "--json", check=True)
    report = json.loads(result.stdout)
    png = simulated_session / "derived" / "plots" / "quicklook.png"
    assert Path(report["out"]) == png.resolve()
    assert png.read_bytes()[:8] == PNG_MAGIC and 20_000 < png.stat().st_size < 400_000
    assert report["title"] == simulated_session.name
    panels = {p["name"]: p for p in report["panels"]}
    manifest = json.loads((simulated_session / "manifest.json").read_text())
    assert set(manifest["streams"]) | {"rates", "labels"} == set(panels)
    assert panels["fps"]["shows"] == "pedal states" and panels["emht"]["shows"] == "EmHT positions"
    assert "detection gaps" in panels["handkp"]["shows"]
    assert report["gaps"] == []


def test_plot_never_writes_into_the_recording(simulated_session: Path) -> None:
    refused = midas("plot", str(simulated_session), "--out", str(simulated_session / "streams" / "x.png"))
    assert refused.returncode == 2 and not (simulated_session / "streams" / "x.png").exists()


def test_plot_shades_the_gap_of_a_device_outage(tmp_path: Path) -> None:
    midas("record", "--simulate", "--device", "emht=sim://emht?rate=240&sensors=4&dropout_at=1.5&dropout_for=0.8",
          "--duration", "3", "--out", str(tmp_path), "--subject", "1", "--task", "t", "--trial", "1", "--no-tui",
          check=True)
    (session,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    target = tmp_path / "look" / "page.png"
    report = json.loads(midas("plot", str(session), "--json", "--out", str(target), check=True).stdout)
    assert Path(report["out"]) == target.resolve() and target.read_bytes()[:8] == PNG_MAGIC
    kinds = {(g["stream"], g["kind"]) for g in report["gaps"]}
    assert ("emht", "seq_gap") in kinds and ("emht", "outage") in kinds
    seq_gap = next(g for g in report["gaps"] if g["kind"] == "seq_gap")
    assert seq_gap["missing"] > 0 and 1.0 < seq_gap["start_s"] < seq_gap["end_s"] < 3.0
    assert "labels" not in {p["name"] for p in report["panels"]}


def test_rig_check_simulated_lists_every_device_with_its_rate(tmp_path: Path) -> None:
    result = midas("rig", "check", "--simulate", "--seconds", "1", "--json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    devices = {d["device"]: d for d in report["devices"]}
    assert set(devices) == {"emht", "fps", "video", "handkp"}
    for device in devices.values():
        assert device["state"] == "ok", device
        for stream in device["streams"].values():
            assert stream["samples"] > 0 and stream["measured_hz"] > 0
            assert 0.5 * stream["nominal_hz"] < stream["measured_hz"] < 1.5 * stream["nominal_hz"]
    assert not any(tmp_path.iterdir()), "rig check writes nothing"


def test_rig_check_with_an_unreachable_device_exits_3_naming_it_and_writes_nothing(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text('[rig]\nname = "bad"\nplatform = "davinci-xi"\n\n'
                   '[devices.emht]\nurl = "fob:///dev/nonexistent?rate=200&sensors=4"\n\n'
                   '[devices.fps]\nurl = "sim://fps?rate=250&channels=9"\n')
    work = tmp_path / "cwd"
    work.mkdir()
    before = set(os.listdir(tmp_path))
    result = midas("rig", "check", str(rig), "--seconds", "1", cwd=work)
    assert result.returncode == 3, result.stderr
    assert "emht" in result.stderr and "failed" in result.stderr
    assert "/dev/nonexistent" in result.stdout
    assert set(os.listdir(tmp_path)) == before and not any(work.iterdir())


def test_rig_check_needs_a_rig_or_simulate() -> None:
    result = midas("rig", "check")
    assert result.returncode == 2
    assert "--simulate" in result.stderr


def test_rig_show_lists_the_default_rigs_devices_and_opens_none(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text('[rig]\nname = "lab"\nplatform = "davinci-xi"\n\n'
                   '[devices.emht]\nurl = "fob:///dev/nonexistent?rate=200&sensors=4"\n')
    result = midas("rig", "show", "--json", env={"MIDAS_RIG": str(rig)}, check=True)  # no device opened: exit 0
    shown = json.loads(result.stdout)
    assert shown["name"] == "lab" and shown["source"] == str(rig)
    assert shown["devices"] == {"emht": {"url": "fob:///dev/nonexistent?rate=200&sensors=4", "kind": "emht"}}
    assert "emht" in midas("rig", "show", "--simulate", check=True).stdout


def test_plot_draws_markers_as_lines_not_as_a_panel(tmp_path: Path) -> None:
    from helpers.cli import SPEC
    from midas_cli.clock import HostClock
    from midas_cli.record.markers import events_spec
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    clock = HostClock.anchored_now()
    events = events_spec()
    writer = SessionWriter.create(tmp_path, SessionMetadata("7", "demo", 1), clock,
                                  {"demo": {"kind": "test"}, "operator": {"kind": "operator"}}, [SPEC, events])
    t0 = clock.now_ns()
    writer.append("demo", SPEC.format_rows([(i, t0 + i * 10_000_000, i * 0.5) for i in range(200)]))
    writer.append("events", events.format_rows([(0, t0 + 500_000_000, 'needle "in", 1', "mark"),
                                                (1, t0 + 1_200_000_000, "knot", "key")]))
    writer.finalize("complete", "test", t0 + 2_000_000_000, {})
    report = json.loads(midas("plot", str(writer.folder), "--json", check=True).stdout)
    panels = {p["name"]: p for p in report["panels"]}
    assert "events" not in panels, "marker text is not drawn as a signal"
    assert panels["markers"] == {"name": "markers", "stream": "events", "shows": "2 marker(s), dotted"}
