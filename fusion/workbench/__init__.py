"""The model workbench: compare the model with a recording, find where it fails, rank the
effects that would explain it.
"""
