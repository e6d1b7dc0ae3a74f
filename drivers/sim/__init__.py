"""Simulated hardware and the simulated world (subjects) the simulators see."""
