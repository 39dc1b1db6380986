"""Training losses: each a pure function of tensors, tested on cases with known answers."""
