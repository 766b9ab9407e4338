"""The ``armfusion`` command line: ``main.py`` is the entry point and the table of commands,
``common.py`` what every command shares, one module per command or group of commands.
"""
