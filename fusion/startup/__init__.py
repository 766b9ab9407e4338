"""The startup solve: every joint angle of a still arm from gravity, with sigma and flags.

``solve.py`` finds the angles (``solve_still``) and is where the startup's public names are
imported from; it reads as its steps, each in a module of its own:

- ``settings.py``: :class:`StartupSettings`, every threshold;
- ``readings.py``: the still readings (a recording's still window averaged, with checks);
- ``problem.py``: the weighted least-squares problem of one window and its batched LM,
  compiled in ``kernels.py`` on the gravity chain's core (``models/gravity_kernels.py``);
- ``branches.py``: the closed-form branches, their combinations, the thesis's method;
- ``prior.py``: what is known before the window (:class:`StartupPrior`) and how it chooses;
- ``confidence.py``: sigmas beyond the linear ones (profile, weak-joint sweep, rivals);
- ``moves.py``: the unlocking and disambiguating moves, and the prior a counted move carries;
- ``results.py``: what the solve gives (:class:`StartupResult` and its parts);
- ``tilt_only.py``: an arm with no joints, its base's tilt from its IMU alone.

``static.py`` finds the still stretches of a recording and ``pose_store.py`` keeps the pose
saved at the last clean shutdown.
"""
