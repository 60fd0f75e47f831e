"""Data shipped with vprbench: dataset manifests and method presets (TOML)."""
