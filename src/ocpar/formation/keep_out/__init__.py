"""Keeping agents apart and clear of obstacles: closest approach, obstacles, separation rounds."""
