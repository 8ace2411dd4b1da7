"""Device simulators that speak each hardware adapter's real wire protocol, for tests and `gd2p bridge selftest`.

    dynamixel.py   a Dynamixel Protocol 2.0 bus of X-series motors on a pty (LEAP hand)
    allegro.py     an Allegro hand V5 on a python-can bus (virtual or real interface)
    xarm.py        a fake xArm controller at the xarm-python-sdk transport boundary

They model the devices' protocol and a simple first-order joint response, not their dynamics.
"""
