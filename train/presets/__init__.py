"""Training presets shipped as package data (YAML, one per dataset and stage)."""
