"""armfusion: fusion layer (calibration, tracking, diagnosis, service, CLI)."""
