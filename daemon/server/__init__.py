"""The long-running daemon process: the service that brings the real rig up and serves it, the
control socket and its subscriptions, systemd notifications and the event loop's lag, measured.
"""
