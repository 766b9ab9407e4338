"""The model workbench: compare the model with a recording, find where it fails, rank the
effects that would explain it. The entry is ``diagnose.py``; its docstring says which
neighbour holds which part.
"""
