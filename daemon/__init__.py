"""The rig daemon: sequences a scan (depth sweep, TSDF, focus plan, capture) and owns time."""
