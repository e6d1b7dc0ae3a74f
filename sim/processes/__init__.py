"""Each simulated device as its own OS process (``tbp sim motor|phone|panel``), on loopback."""
