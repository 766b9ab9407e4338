"""The ``armfusion`` command line: ``main.py`` is the entry point and the table of commands,
``options.py`` the options several commands take, ``common.py`` what every command does
alike, then one module per command or group of commands (a large one with its parts beside
it: ``drivers_run``, ``drivers_faults``, ``drivers_report``; ``diagnose_report``).
"""
