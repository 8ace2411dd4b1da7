"""The hand `leap`: a LEAP hand over dynamixel-sdk (config.py, robot.py; fake.py: a Protocol 2.0 bus on a pty)."""
