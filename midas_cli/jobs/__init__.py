"""Batch runs of independent units (a session to align, a fold to train) on this machine or as a SLURM
job array, resumable and observable through a run folder (``rundir.py``).

* ``rundir.py``  the run folder: ``plan.json`` (the task, every unit's arguments and input fingerprint),
  per-unit markers (``units/<k>/running.json``, ``done.json``, ``failed.json``), ``logs/unit-<k>.log``.
* ``runner.py``  runs one unit: marks it running, calls the task's function, writes done (with its
  result and fingerprint) or failed (with the last error line). The same function runs a unit locally
  and in a SLURM array task (``python -m midas_cli jobs run-unit RUN_DIR --unit K``).
* ``local.py``   the local executor (in this process, or ``--jobs N`` worker processes).
* ``slurm.py``   the SLURM executor: an ``sbatch --array`` script per submission, squeue to observe it.
* ``status.py``  each unit's state (pending, queued, running, done, stale, failed) and waiting for them.
* ``options.py`` the executor options as given (``BatchOptions``) and checked (``ExecutorChoice``).
* ``batch.py``   a plan run end to end: run folder, skip the done units, run here or submit, wait, collect.
* ``tasks.py``   the registry of unit tasks: each task's name and its units module (imported on use).

Nothing here knows what a unit does: ``tasks.py`` names each task's module as a string (the packages
with units sit above this one) and its ``run_unit`` (args dict -> result dict) is imported when a unit
runs. Nothing here prints: ``batch.run_plan`` tells its caller's ``Watch``.
"""
