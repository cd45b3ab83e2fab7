"""Simulators that speak the real wire protocols, fed by one simulated world (physics/)."""
