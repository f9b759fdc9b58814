"""Console commands (tyro CLIs) of nerfuser_ns."""
