"""Command-line interface: parsing only. Everything else lives in ``vo``."""
