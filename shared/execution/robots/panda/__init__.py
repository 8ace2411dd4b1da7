"""The arm `panda`: a Franka Research 3 over franky-control (config.py: settings and limits; robot.py)."""
