"""armfusion: fusion layer (calibration, tracking, diagnosis, service, CLI)."""
__version__ = "0.1.0"
