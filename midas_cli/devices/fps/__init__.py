"""The FPS pedal board: line-protocol codec, serial driver, pty emulator and threshold calibration."""
