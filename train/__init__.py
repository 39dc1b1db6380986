"""Self-supervised training of the flow and depth networks (TrianFlow's three stages)."""
