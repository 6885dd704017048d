"""Parameters: the robot's and the motors' physical description, the gyro's range table, and the
one check for a finite number from outside.

A leaf: the config reads these, computation and the drivers use them, and it imports nothing
of ddrt, so the config and computation need not import each other both ways.
"""
