"""Importers of common logger exports into the drive-log contract (``driveby import FORMAT PATH``).

``sensor_logger``: the "Sensor Logger" phone app's CSV export (format ``phone-csv``); ``cli``: the
subcommand's arguments and dispatch.
"""
