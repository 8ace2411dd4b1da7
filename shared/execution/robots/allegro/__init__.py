"""The hand `allegro`: an Allegro hand V5 over python-can (config.py, robot.py, protocol.py; fake.py: a V5 hand)."""
