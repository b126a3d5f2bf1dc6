"""DRVS: a Distributed Robotic Vision Service.

Robots ask for *what* (a filter_def) and *where* (a floor region); the server forwards the request to
the camera nodes that see that region; the cameras stream object locations back to the robot.
"""

__version__ = "0.1.0"
