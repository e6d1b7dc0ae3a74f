"""Real hardware drivers (CANopen motor, ADB phone cameras, operator panel, depth cameras).

``drivers.sim`` holds the simulators that impersonate each device at its protocol; runtime
code outside the simulated-hardware wiring never imports it.
"""
