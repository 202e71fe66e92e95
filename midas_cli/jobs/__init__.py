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

Nothing here knows what a unit does: a task's function (args dict -> result dict) is passed in by the
command that plans the run (see ``midas_cli/commands/executor.py`` for the registry of tasks).
"""
