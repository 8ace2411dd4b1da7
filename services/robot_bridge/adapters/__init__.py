"""Hardware adapters behind the Backend contract (services/robot_bridge/backend.py).

Each imports its vendor package lazily, so the bridge runs without the optional extras installed:

    franka.py   Franka Research 3 via franky-control          (extra: franka)
    xarm.py     UFactory xArm7 via xarm-python-sdk            (extra: xarm)
    leap.py     LEAP hand via dynamixel-sdk, Protocol 2.0     (extra: leap)
    allegro.py  Allegro hand V5 via python-can                (extra: allegro)
"""
