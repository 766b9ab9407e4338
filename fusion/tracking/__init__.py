"""Tracking: the unscented Kalman tracker of the joints and the chair's heading, the
sigma-point filter it runs on and their compiled kernels.
"""
