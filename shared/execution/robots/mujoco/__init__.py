"""The MuJoCo arm + hand: a second execution engine behind the robot contract (config, model, robot, decompose)."""
