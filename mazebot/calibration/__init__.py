"""``mazebot calibrate``: the robot measures its own wiring and geometry, the lidar's view of the walls as the ruler."""
