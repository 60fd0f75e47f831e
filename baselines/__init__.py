"""VPR-trained baselines, registered through the public plugin API (entry points in pyproject.toml)."""
