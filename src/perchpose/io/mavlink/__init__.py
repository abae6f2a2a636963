"""MAVLink: one link a vehicle on its own thread (``link``, with ``timesync``), and what goes on it:
LANDING_TARGET (``landing_target`` builds the message, ``landing_target_sink`` sends it),
TARGET_RELATIVE (``target_relative``, its dialect in ``dialects/``) and the pilot's setpoints
(``pilot``). Needs the ``mavlink`` extra."""
