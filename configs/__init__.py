"""YAML config presets, one per stage."""
