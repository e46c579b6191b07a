"""The coroutines that join devices, SLAM, the planner and the motors (thin glue)."""
