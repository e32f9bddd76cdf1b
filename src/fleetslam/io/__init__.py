"""Standard file formats: PLY point clouds, TUM trajectories."""
