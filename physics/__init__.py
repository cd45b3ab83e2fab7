"""The model of the world: frames, table, sensor model, heading, calibration fits. Pure numpy/scipy, no I/O."""
