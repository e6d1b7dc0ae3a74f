"""The rig as the daemon sees it: the device protocols and the device set (real or simulated),
the hardware file, bring-up and re-probing, the beam's encoder stream, the phones' clock mapping,
the state machine that latches faults and the safety monitor that trips it.
"""
