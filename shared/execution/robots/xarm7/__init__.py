"""The arm `xarm7`: a UFactory xArm7 over xarm-python-sdk (config.py, robot.py; fake.py: its protocol fake)."""
