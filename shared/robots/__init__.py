"""Robot models: the arms (`arms`), the hands (`hands`, with their packaged assets) and their limits (`robot_limits`)."""
