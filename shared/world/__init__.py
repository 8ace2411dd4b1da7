"""The world a push happens in: objects, perception, simulation, and the one judge of a push.

`objects` (the object library), `perception` (objects from point clouds), `sim` (PyBullet worlds and the
simulated robot's plan runner), `object_refs` (ObjectRef -> ObjectModel), `bps` (an object's BPS encoding),
`fixed_poses` (the fixed spatula hand pose), `push_outcome` (where the object ended up against its goal).
"""
