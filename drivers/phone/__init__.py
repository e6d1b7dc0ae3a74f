"""Phone cameras: the capture agent's protocol, focus calibration tables and PhoneCamera over ADB."""
