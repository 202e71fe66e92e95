"""Batch runs without SLURM (issue 16): run folders, done markers and fingerprints, stale and failed units,
`midas jobs status`, the sbatch script a SLURM submission would use, and the executor options' checks.
The same runs on a real SLURM are tests/jobs/test_slurm.py."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from helpers.analysis_sessions import raven_session
from helpers.cli import midas
from midas_cli.errors import ConfigError
from midas_cli.jobs.rundir import Plan, RunDir, Unit
from midas_cli.jobs.runner import run_unit
from midas_cli.jobs.slurm import SlurmSettings, array_spec, sbatch_arguments, script
from midas_cli.jobs.status import statuses


def double(args: dict) -> dict:
    if args["x"] < 0:
        raise ValueError(f"negative x: {args['x']}\nsecond line")
    return {"result": 2 * args["x"], "outputs": []}


def test_units_run_once_then_skip_until_their_fingerprint_changes(tmp_path):
    run = RunDir(tmp_path / "run")
    plan = run.write_plan(Plan("double", [Unit("a", {"x": 1}, "f1"), Unit("b", {"x": -1}, "f2")]))
    assert run_unit(run, 0, double)["result"] == 2
    with pytest.raises(ValueError):
        run_unit(run, 1, double)
    found = {s.name: s for s in statuses(run)}
    assert found["a"].state == "done" and found["b"].state == "failed"
    assert found["b"].error == "ValueError: negative x: -1"  # the headline, not the traceback's tail
    assert found["b"].log == str(run.log(1)) and "negative x" in run.log(1).read_text()
    calls = []
    run_unit(run, 0, lambda args: calls.append(args) or {"result": 0})
    assert calls == []  # done with the same fingerprint: skipped
    run.write_plan(Plan("double", [Unit("a", {"x": 1}, "f1-changed"), plan.units[1]]))
    assert statuses(run)[0].state == "stale"
    run.write_marker(1, "running", {"host": os.uname().nodename, "pid": 2**22 + 12345})  # a dead process
    run.clear(1, ("failed",))
    assert statuses(run)[1].state == "failed" and "died" in statuses(run)[1].error
    with pytest.raises(ConfigError, match="belongs to a 'double' run"):
        run.write_plan(Plan("other", []))


def test_slurm_settings_flags_over_config_and_the_sbatch_arguments():
    settings = SlurmSettings.merged({"time": "00:05:00", "gpus": None, "mem": None},
                                    {"time": "01:00:00", "mem": "2G", "gpus": 1, "partition": "gpu",
                                     "array_parallelism": 4, "account": "lab"})
    assert (settings.time, settings.mem, settings.gpus, settings.partition) == ("00:05:00", "2G", 1, "gpu")
    arguments = sbatch_arguments(RunDir("/shared/run \"x\""), "align", [0, 1, 2, 5, 7, 8], settings)
    assert arguments == ["--job-name=midas-align", "--array=0-2,5,7-8%4", '--output=/shared/run "x"/logs/unit-%a.log',
                         "--partition=gpu", "--time=00:05:00", "--mem=2G", "--account=lab", "--gres=gpu:1"]
    text = script()
    assert "#SBATCH" not in text and "gpu" not in text and "/shared/run" not in text  # nothing from a flag or file
    assert text.rstrip().endswith('jobs run-unit "$1" --unit "$SLURM_ARRAY_TASK_ID"')
    assert array_spec([3], None) == "3"
    for good in ("10", "10:30", "1:00:00", "2-12", "2-12:30", "2-12:30:00"):  # SLURM's six time formats
        assert SlurmSettings(time=good).sbatch_options() == [f"--time={good}"]
    with pytest.raises(ConfigError, match="'%' and"):
        sbatch_arguments(RunDir("/shared/run%j"), "align", [0], settings)


@pytest.mark.parametrize(("config", "flag", "gpus"), [("", None, 1), ("[slurm]\ngpus = 2\n", None, 2),
                                                      ("[slurm]\ngpus = 2\n", 0, 0), ("[slurm]\ngpus = 0\n", None, 1)])
def test_units_that_need_a_gpu_ask_slurm_for_one_unless_the_flag_says_otherwise(tmp_path, monkeypatch, config, flag,
                                                                                  gpus):
    from midas_cli.jobs.options import BatchOptions

    (tmp_path / "config.toml").write_text(config, encoding="utf-8")
    monkeypatch.setenv("MIDAS_CONFIG", str(tmp_path / "config.toml"))
    options = BatchOptions(executor="slurm", slurm_gpus=flag)
    assert options.choice(gpu=True).slurm.gpus == gpus
    assert options.choice().slurm.gpus == (flag if flag is not None else int(config[-2:-1] or 0))  # no GPU asked
    local = BatchOptions(jobs=3).choice(gpu=True)
    assert (local.executor, local.jobs, local.slurm, local.in_process) == ("local", 3, None, False)


def test_a_batch_command_declares_the_executor_options_once_and_gets_them_as_one_object(tmp_path):
    import typer
    from typer.testing import CliRunner

    from midas_cli.commands.executor import batch_command
    from midas_cli.jobs.options import BatchOptions

    app, seen = typer.Typer(), []

    @app.command()
    @batch_command
    def work(name: str = typer.Argument(...), loud: bool = typer.Option(False, "--loud"), *, batch) -> None:
        """Work on NAME."""
        seen.append((name, loud, batch))

    @app.command()
    def other() -> None:
        """Another command (so that typer keeps the command names)."""

    runner = CliRunner()
    given = ["work", "a", "--run-dir", str(tmp_path), "--executor", "slurm", "--slurm-gpus", "2", "--no-wait", "--loud"]
    assert runner.invoke(app, given).exit_code == 0
    assert seen == [("a", True, BatchOptions(executor="slurm", run_dir=tmp_path, no_wait=True, slurm_gpus=2))]
    shown = runner.invoke(app, ["work", "--help"], env={"COLUMNS": "200", "NO_COLOR": "1"}).output
    assert "Work on NAME." in shown and shown.index("--loud") < shown.index("Executor") < shown.index("--executor")
    for flag in EXECUTOR_FLAGS:
        assert flag in shown[shown.index("Executor"):], flag


EXECUTOR_FLAGS = ("--executor", "--jobs", "--run-dir", "--no-wait", "--slurm-partition", "--slurm-time", "--slurm-mem",
                  "--slurm-gpus", "--slurm-array-parallelism")


def test_the_seven_batch_commands_have_the_executor_options_in_their_executor_panel():
    import typer.main

    from midas_cli.commands.main import build_app

    root = typer.main.get_command(build_app())
    paths = [["align"], ["train", "gestures"], ["train", "ablation"], ["simulate", "dataset"],
             ["ground-truth", "pedals"], ["extract", "handkp"], ["features", "image"]]
    for path in paths:
        command = root
        for name in path:
            command = command.commands[name]
        panel = [p.opts[0] for p in command.params if getattr(p, "rich_help_panel", None) == "Executor"]
        assert tuple(panel) == EXECUTOR_FLAGS, path


@pytest.mark.parametrize(("bad", "named"), [
    ({"time": "soon"}, "--slurm-time"), ({"time": "10\n"}, "--slurm-time"), ({"time": "1:2:3:4"}, "--slurm-time"),
    ({"time": "\uff11\uff10"}, "--slurm-time"), ({"mem": "lots"}, "--slurm-mem"), ({"mem": "8GB"}, "--slurm-mem"),
    ({"array_parallelism": 0}, "--slurm-array-parallelism"), ({"gpus": -1}, "--slurm-gpus"),
    ({"partition": "gpu\ntouch /tmp/INJ"}, "--slurm-partition"), ({"partition": "gpu;id"}, "--slurm-partition"),
    ({"account": "lab --wrap=id"}, "[slurm] account"), ({"qos": "$(id)"}, "[slurm] qos"),
    ({"cpus_per_task": 0}, "[slurm] cpus_per_task")])
def test_slurm_settings_outside_slurms_grammar_are_refused_naming_the_setting(bad, named):
    with pytest.raises(ConfigError) as caught:
        SlurmSettings(**bad)
    assert str(caught.value).startswith(f"{named} {next(iter(bad.values()))!r} ") and "\n" not in str(caught.value)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("jobs-sessions")
    return [raven_session(root, trial=k, duration_s=3.0, seed=k) for k in (1, 2, 3)]


def test_align_with_a_run_folder_resumes_and_reports_a_failed_session(sessions, tmp_path):
    data = [Path(shutil.copytree(s, tmp_path / s.name)) for s in sessions]
    broken = Path(shutil.copytree(sessions[0], tmp_path / "broken"))
    (broken / "manifest.json").write_text("[]", encoding="utf-8")
    run = tmp_path / "run"
    args = ["align", str(data[0]), str(broken), str(data[1]), "--jobs", "2", "--run-dir", str(run)]
    first = midas(*args, env={"MIDAS_PROGRESS_INTERVAL_S": "0"})
    assert first.returncode == 4, first.stderr
    assert "1 of 3 sessions did not finish" in first.stderr and "broken: failed" in first.stderr
    assert "progress: aligning sessions: 3/3" in first.stderr
    assert data[0].name in first.stdout and data[1].name in first.stdout  # the others' table
    status = json.loads(midas("jobs", "status", str(run), "--json", check=True).stdout)
    assert [u["state"] for u in status["units"]] == ["done", "failed", "done"]
    assert status["units"][1]["log"] == str(run.resolve() / "logs" / "unit-1.log")
    shutil.rmtree(broken)
    shutil.copytree(sessions[2], broken)  # repaired
    second = midas(*args, "--json")
    assert second.returncode == 0, second.stderr
    assert "2 of 3 units done already" in second.stderr and len(json.loads(second.stdout)) == 3
    assert json.loads((run / "submissions.json").read_text())[-1]["units"] == [1]


@pytest.mark.parametrize(("extra", "needle"), [(["--no-wait"], "--no-wait needs --executor slurm"),
                                               (["--slurm-time", "1:00"], "--slurm-time needs --executor slurm"),
                                               (["--executor", "slurm", "--jobs", "2"], "--jobs is for"),
                                               (["--executor", "cloud"], "--executor must be")])
def test_executor_options_are_checked(sessions, extra, needle):
    result = midas("align", str(sessions[0]), *extra)
    assert result.returncode == 2 and needle in result.stderr


def fake_slurm(tmp_path: Path, config: str) -> tuple[dict[str, str], Path]:
    """An environment whose sbatch (and scontrol) are scripts that record their arguments, one per line, and
    a config file holding ``config``; the file sbatch writes."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "sbatch-args"
    (bin_dir / "sbatch").write_text(f"#!/bin/sh\nprintf '%s\\n' \"$@\" > '{calls}'\necho 4242\n")
    (bin_dir / "scontrol").write_text("#!/bin/sh\necho 'MaxArraySize = 1001'\n")
    for tool in bin_dir.iterdir():
        tool.chmod(0o755)
    (tmp_path / "config.toml").write_text(config, encoding="utf-8")
    return {"PATH": f"{bin_dir}:{os.environ['PATH']}", "MIDAS_CONFIG": str(tmp_path / "config.toml")}, calls


@pytest.mark.parametrize(("config", "flags", "named"), [
    ('[slurm]\npartition = "gpu\\ntouch INJ"\n', [], "[slurm] partition = 'gpu\\ntouch INJ'"),
    ('[slurm]\naccount = "lab\\ntouch INJ"\n', [], "[slurm] account = 'lab\\ntouch INJ'"),
    ("", ["--slurm-partition", "gpu\ntouch INJ"], "--slurm-partition 'gpu\\ntouch INJ'")])
def test_a_slurm_setting_with_a_command_in_it_is_refused_and_nothing_is_submitted(sessions, tmp_path, config, flags,
                                                                                   named):
    env, calls = fake_slurm(tmp_path, config)
    result = midas("align", str(sessions[0]), "--executor", "slurm", "--run-dir", str(tmp_path / "run"), "--no-wait",
                   *flags, env=env, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().count("\n") == 0 and named in result.stderr
    assert not calls.exists() and not (tmp_path / "INJ").exists() and not (tmp_path / "run").exists()


def test_valid_slurm_settings_reach_sbatch_as_its_arguments(sessions, tmp_path):
    env, calls = fake_slurm(tmp_path, '[slurm]\naccount = "surgical-ai"\nqos = "normal"\nmem = "500M"\n')
    run = tmp_path / "run dir"
    result = midas("align", str(sessions[0]), "--executor", "slurm", "--run-dir", str(run), "--no-wait",
                   "--slurm-partition", "gpu,debug", "--slurm-time", "1-02:00", env=env)
    assert result.returncode == 0, result.stderr
    arguments = calls.read_text().splitlines()
    assert arguments == ["--parsable", "--job-name=midas-align", "--array=0", f"--output={run.resolve()}/logs/unit-%a.log",
                         "--partition=gpu,debug", "--time=1-02:00", "--mem=500M", "--account=surgical-ai",
                         "--qos=normal", str(run.resolve() / "slurm-0.sh"), str(run.resolve())]
    assert json.loads((run / "submissions.json").read_text())[0]["sbatch"] == arguments[1:]
    assert "surgical-ai" not in (run / "slurm-0.sh").read_text()


def test_a_slurm_task_that_left_the_queue_without_a_marker_is_failed(tmp_path, monkeypatch):
    from midas_cli.jobs import slurm

    run = RunDir(tmp_path / "run")
    run.write_plan(Plan("double", [Unit("a", {"x": 1}, "f"), Unit("b", {"x": 2}, "f"), Unit("c", {"x": 3}, "f")]))
    run.add_submission({"executor": "slurm", "job_id": "41", "units": [0, 1, 2]})
    run.write_marker(0, "running", {"host": "node7", "pid": 1, "job_id": "41", "task_id": "0"})
    run.log(0).write_text("step\nslurmstepd: error: *** JOB 41 ON node7 CANCELLED AT 2026-01-01 DUE TO TIME LIMIT ***\n")
    monkeypatch.setattr(slurm, "queued", lambda job: {2: "PENDING"})
    found = statuses(run)
    assert [s.state for s in found] == ["failed", "failed", "queued"]
    assert "ended without a result" in found[0].error and "TIME LIMIT" in found[0].error
    assert "without starting the unit" in found[1].error
    monkeypatch.setattr(slurm, "queued", lambda job: None)  # squeue cannot be asked: nothing concluded
    assert [s.state for s in statuses(run)] == ["running", "queued", "queued"]


def test_every_units_module_is_registered_once_under_its_own_task_name():
    import importlib

    from midas_cli.jobs.tasks import UNIT_MODULES, task_function

    package = Path(__file__).resolve().parents[2] / "midas_cli"
    found = {".".join(p.relative_to(package.parent).with_suffix("").parts) for p in package.rglob("*units.py")}
    assert found == set(UNIT_MODULES.values())  # every units module in the tree, each once
    assert len(found) == len(UNIT_MODULES) == 7
    for task, name in UNIT_MODULES.items():
        module = importlib.import_module(name)
        assert module.TASK == task and task_function(task) is module.run_unit, name


@pytest.mark.parametrize("hostile", ["nope", "", "midas_cli.analysis.align_units", "__class__", None, 3, ["align"]])
def test_only_a_registered_task_name_from_a_run_folder_resolves(hostile):
    from midas_cli.jobs.tasks import task_function

    with pytest.raises(ConfigError, match="unknown unit task"):
        task_function(hostile)


def test_run_unit_refuses_a_run_folder_of_an_unknown_task_in_one_line(tmp_path):
    run = RunDir(tmp_path / "run")
    run.write_plan(Plan("os.system", [Unit("a", {"x": 1}, "f")]))
    result = midas("jobs", "run-unit", str(run.path), "--unit", "0")
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().count("\n") == 0 and "unknown unit task 'os.system'" in result.stderr
    assert not run.marker(0, "running").exists() and not run.marker(0, "failed").exists()


def test_an_ablation_cell_trained_on_other_data_is_moved_aside_and_trained_again(tmp_path):
    from helpers.gesture_sessions import write_gesture_session
    from midas_cli.jobs.tasks import task_function
    from midas_cli.models.ablation import GridRow
    from midas_cli.models.ablation_units import TASK, plan_units
    from midas_cli.models.train import TrainConfig

    sessions = [write_gesture_session(tmp_path / "data", "B", k + 1, n_frames=120, seed=k) for k in range(2)]
    base = TrainConfig(split="loto", fold=0, epochs=1, seed=1)
    out, run = tmp_path / "out", RunDir(tmp_path / "run")

    def cell() -> dict:
        unit = plan_units(sessions, [GridRow(("emht",), ("pos",), False)], ["baseline"], base, out, cv=False)[0]
        run.write_plan(Plan(TASK, [unit]))
        return run_unit(run, 0, task_function(TASK))

    first = cell()
    assert first["result"]["model"] == "Baseline (LR)" and (out / "runs" / "baseline__emht__pos").is_dir()
    assert cell()["finished"] == first["finished"]  # same data: skipped
    labels = sessions[1] / "labels" / "gestures.csv"
    lines = labels.read_text().splitlines()
    labels.write_text("\n".join(lines[:1] + [line.replace("G2", "G3") for line in lines[1:]]) + "\n")
    cell()
    assert (out / "runs" / "baseline__emht__pos.stale-0" / "metrics.json").is_file()
    assert (out / "runs" / "baseline__emht__pos" / "metrics.json").is_file()


def test_a_run_larger_than_the_clusters_max_array_size_is_refused(tmp_path, monkeypatch):
    from midas_cli.jobs import slurm

    run = RunDir(tmp_path / "run")
    run.write_plan(Plan("double", [Unit(str(k), {"x": k}, "f") for k in range(12)]))
    monkeypatch.setattr(slurm, "max_array_size", lambda: 10)
    with pytest.raises(ConfigError, match="12 units but the cluster's MaxArraySize is 10"):
        slurm.submit(run, "double", list(range(12)), SlurmSettings())
    assert not list(run.path.glob("slurm-*.sh"))


def test_a_stop_signal_to_the_batch_process_alone_stops_its_workers_too(tmp_path):
    """`kill PID` (a script's timeout, a scheduler) signals the batch process, not its process group: the
    worker processes must stop with it, not train on for minutes while the batch waits for them."""
    import signal
    import subprocess
    import sys

    from helpers.cli import wait_for
    from helpers.gesture_sessions import write_gesture_dataset

    sessions = write_gesture_dataset(tmp_path / "data", n_trials=4, subjects=2, n_frames=200)
    out = tmp_path / "cv"
    command = [sys.executable, "-m", "midas_cli", "train", "gestures", *map(str, sessions), "--model", "mstcn",
               "--modalities", "emht", "--features", "pos", "--epochs", "100000", "--split", "louo", "--fold", "all",
               "--jobs", "2", "--no-baseline", "--out", str(out)]
    batch = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)  # its own group: the signal reaches the batch process only
    try:
        wait_for(lambda: len(list((out / "jobs" / "units").glob("*/running.json"))) == 2, timeout_s=300, step_s=0.2)
        workers = [json.loads(p.read_text())["pid"] for p in (out / "jobs" / "units").glob("*/running.json")]
        batch.send_signal(signal.SIGTERM)
        _, stderr = batch.communicate(timeout=120)  # the units would train for hours
    finally:
        if batch.poll() is None:
            os.killpg(batch.pid, signal.SIGKILL)
    assert batch.returncode == 128 + signal.SIGTERM and "stopped by SIGTERM" in stderr
    for pid in workers:  # reaped by the batch process (a zombie would still answer kill 0)
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    assert not list((out / "jobs" / "units").glob("*/done.json"))  # nothing claims to have finished
