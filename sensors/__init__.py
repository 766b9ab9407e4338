"""armfusion: sensors layer (drivers, fakes, raw samples, recording I/O)."""
