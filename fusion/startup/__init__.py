"""The startup solve: every joint angle of a still arm from gravity, with sigma and flags.

``solve.py`` finds the angles (``solve_still``), ``kernels.py`` is its compiled
Levenberg-Marquardt, ``static.py`` finds the still stretches of a recording and
``pose_store.py`` keeps the pose saved at the last clean shutdown.
"""
