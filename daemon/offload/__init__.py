"""Compute that must not hold the event loop: the compute worker process, the depth sweep handed
to it in shared memory, the TSDF fused there while the beam turns, and the focus plan computed
there.
"""
