"""Depth cameras: the frame type, the camera protocol and the sweep that tags frames with beam angles."""
