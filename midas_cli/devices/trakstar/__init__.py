"""trakSTAR EmHT: FOB RS-232 codec (protocol), its driver (fob://), the ATC3DG backend (atc3dg://), the emulator."""
