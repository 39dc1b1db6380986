"""Reference methods the dense pipeline is benchmarked against (not on the default path)."""
