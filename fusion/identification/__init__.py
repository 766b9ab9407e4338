"""Identification: the parameters of the model's effects fitted from a recording of many
orientations (sensor calibration), and the sensor-calibration article's own model
(``renk.py``) for its reproduction. The fit's entry is ``identify.py``; its docstring says
which neighbour holds which part.
"""
