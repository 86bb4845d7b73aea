"""auxgps: a visual back-up GPS for drones.

Layout
------
core/        pure maths: camera and frames, feature detection, the landmark map, mapping, positioning.
             Takes arrays and dataclasses, returns dataclasses; no files, sockets or clocks.
sim/         the simulated world, camera renderer and flights (evaluation and tests only).
evaluation/  flies simulated missions through the core and scores them against the truth.
config.py    typed configuration read from YAML.
cli.py       the `auxgps` command.
"""

__version__ = "0.1.0"
