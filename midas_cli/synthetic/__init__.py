"""The synthetic world: a simulated surgeon and the synthetic sensors that watch it, with known ground truth.

What lives where:

* ``noise``: deterministic randomness (seeded generators per stream, counter-based hash noise keyed on
  sample time, banks of sinusoids).
* ``schedule``: chunked, lazily generated schedules (minimum-jerk knot curves, event intervals, renewal
  processes, hold-and-reach knots).
* ``hands``: the hand model on the master-controller grips (focus, reaches, grasp cycles, tremor, sensor
  pads); sensor and hand names.
* ``feet``: the foot / FSR pedal-board model (presses, contact bounce, resting foot, ADC counts); pedal
  indices.
* ``surgeon``: ``SurgeonMotion`` (hands + feet + depth-camera keypoints) and its ``MotionConfig``.
* ``gesture_hands``: hands of a simulated trial driven by a gesture sequence (``GestureHands``), on the
  surgeon's hand geometry.
* ``trial_pedals``: pedal presses of a simulated trial (clutch per gesture segment, random pedals) and the
  FSR board's readings of them.
* ``console_video``: frames of a synthetic da Vinci Xi console video with a seeded pedal schedule.
* ``stereo_camera``: a synthetic stereo camera with known geometry (ray-traced textured planes).

Users: the device simulators and emulators (``devices/sim``, ``devices/trakstar``, ``devices/fps``,
``devices/raven``, ``devices/rgbd``) sample it live; ``simulate/`` assembles datasets and files from it
(gesture sequences, ground truth, sessions, the console video file). This package imports only
low-level modules (geometry, errors, ``devices/pedals.py``, ``devices/rgbd/calibration.py``), never
``commands/``, ``analysis/``, ``session/`` or ``simulate/``.
"""
