"""Shipped configuration presets (YAML files read by trianflow_vo.config.load_config)."""
