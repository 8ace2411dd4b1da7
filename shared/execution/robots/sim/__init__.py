"""The simulated arm + hand (PyBullet), the bridge's default robot (config.py, robot.py)."""
