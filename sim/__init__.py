"""The simulated world: the virtual-time loop, simulated subjects (Anny adults), the whole
simulated rig wired to the daemon, and each simulated device as its own process.

The device twins themselves (protocol-level simulators) live in ``drivers.sim``; this package
puts them in a world with a subject and a clock. Runtime code never imports it.
"""
