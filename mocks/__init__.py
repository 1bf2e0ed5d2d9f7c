"""Mock hardware: robot controllers speaking the real protocols, and the O-arm simulator."""
