"""``armfusion import``: a foreign recording (CSV, MATLAB .mat, HDF5) onto an arm's streams.

One idea per module: the column map a user writes (:mod:`~armfusion.fusion.importing.column_map`), the
policy for time stamps that do not increase (:mod:`~armfusion.fusion.importing.stamps`), a stream's
values from its source columns into the unit its config declares
(:mod:`~armfusion.fusion.importing.to_stream`), and the import itself with its summary
(:mod:`~armfusion.fusion.importing.run`). The files are read by :mod:`armfusion.sensors.foreign`, which knows
nothing of arms.
"""
