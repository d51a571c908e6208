"""Capture: rig description, planning, sessions on disk, devices (simulated and real), time-lapse."""
