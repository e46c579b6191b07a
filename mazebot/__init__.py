"""mazebot: a Raspberry Pi robot that maps an unknown maze with a lidar and wheel encoders."""

__version__ = "0.1.0"
