"""Identification: the parameters of the model's effects fitted from a recording of many
orientations (sensor calibration), and the sensor-calibration article's own model
(``renk.py``) for its reproduction.
"""
