"""Core model: geometry, the pose graph and its objective, partitions, fixed poses, precision."""
