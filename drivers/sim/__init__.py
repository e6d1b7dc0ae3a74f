"""Device twins: each simulator impersonates one device at its protocol (CANopen frames over a
socketcand bridge, adbd with the capture agent, the panel's serial lines, depth frames)."""
