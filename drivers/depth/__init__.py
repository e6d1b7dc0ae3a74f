"""Depth cameras: the frame type and camera protocol, live RealSense cameras, recordings (playback, recorder, beam-angle files, npz sweep folders)."""
