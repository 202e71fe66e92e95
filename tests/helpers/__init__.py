"""Helpers shared by the tests (pytest puts tests/ on sys.path, so tests import ``helpers.X``).

* ``cli``: run the real `midas` in a subprocess, wait for recorded rows, build small sessions.
* ``net``: free loopback TCP/UDP ports.
* ``analysis_sessions``: Raven-II-like sessions with known ground truth (align/calibrate/eval).
* ``gesture_sessions``: labelled sessions for the gesture models.
* ``obs_fixture``: a real OBS Studio on a virtual screen; ``lsl_fixture``: LSL on loopback.
* ``trakstar``: the trakSTAR emulator fixture and its expected values.

No test module imports another test module or ``conftest``: what two tests share lives here.
"""
