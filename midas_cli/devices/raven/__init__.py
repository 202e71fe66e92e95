"""Raven-II teleoperation telemetry: the ITP ``u_struct`` UDP packets (codec, listener, emulator)."""
